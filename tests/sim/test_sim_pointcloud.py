"""PCD / PLY writers and readers: round trips, foreign layouts (extra fields, big endian), clear errors."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from openfly_agent.sim.pointcloud import (
    PointCloudError,
    read_pcd,
    read_ply,
    read_points,
    write_pcd,
    write_ply,
    write_points,
)

FINITE = st.floats(-1e4, 1e4, allow_nan=False, width=32)


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
@pytest.mark.parametrize("binary", [True, False])
@settings(max_examples=15, deadline=None)
@given(points=arrays(np.float32, st.tuples(st.integers(0, 40), st.just(3)), elements=FINITE))
def test_round_trip_is_exact_in_float32(tmp_path_factory, suffix, binary, points):
    path = tmp_path_factory.mktemp("pc") / f"cloud{suffix}"
    write_points(path, points, binary=binary)
    back = read_points(path)
    assert back.dtype == np.float64 and back.shape == points.shape
    np.testing.assert_array_equal(back, points.astype(np.float64))


def test_pcd_header_is_the_v07_layout(tmp_path):
    write_pcd(tmp_path / "a.pcd", np.array([[1.5, -2.0, 3.25]]), binary=False)
    text = (tmp_path / "a.pcd").read_text().splitlines()
    assert text[1:11] == [
        "VERSION 0.7", "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1", "WIDTH 1", "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0", "POINTS 1", "DATA ascii",
    ]  # fmt: skip
    assert text[11] == "1.5 -2 3.25"


def test_pcd_with_extra_fields_counts_and_nan_rows(tmp_path):
    header = (
        "VERSION 0.7\nFIELDS intensity x y z normal\nSIZE 2 8 4 4 4\nTYPE U F F F F\nCOUNT 1 1 1 1 3\n"
        "WIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA {}\n"
    )
    dtype = np.dtype([("i", "<u2"), ("x", "<f8"), ("y", "<f4"), ("z", "<f4"), ("n", "<f4", (3,))])
    rec = np.zeros(3, dtype)
    rec["x"], rec["y"], rec["z"] = [1, 2, np.nan], [4, 5, 6], [7, 8, 9]
    (tmp_path / "b.pcd").write_bytes(header.format("binary").encode() + rec.tobytes())
    np.testing.assert_array_equal(read_pcd(tmp_path / "b.pcd"), [[1, 4, 7], [2, 5, 8]])
    rows = "\n".join(f"{r['i']} {r['x']} {r['y']} {r['z']} 0 0 1" for r in rec)
    (tmp_path / "a.pcd").write_text(header.format("ascii") + rows + "\n")
    np.testing.assert_array_equal(read_pcd(tmp_path / "a.pcd"), [[1, 4, 7], [2, 5, 8]])


def test_ply_big_endian_with_colours_and_faces(tmp_path):
    header = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty double x\nproperty double y\n"
        "property double z\nproperty uchar red\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    rec = np.array(
        [(1.0, 2.0, 3.0, 255), (4.0, 5.0, 6.0, 0)],
        dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("r", "u1")],
    )
    (tmp_path / "c.ply").write_bytes(header.encode() + rec.tobytes() + b"\x03" + b"\x00" * 12)
    np.testing.assert_array_equal(read_ply(tmp_path / "c.ply"), [[1, 2, 3], [4, 5, 6]])


def test_bad_files_name_the_file_and_the_field(tmp_path):
    (tmp_path / "noy.pcd").write_text("FIELDS x z\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nPOINTS 0\nDATA ascii\n")
    with pytest.raises(PointCloudError, match="noy.pcd.*FIELDS has no 'y'"):
        read_pcd(tmp_path / "noy.pcd")
    (tmp_path / "lzf.pcd").write_text("FIELDS x y z\nPOINTS 0\nDATA binary_compressed\n")
    with pytest.raises(PointCloudError, match="lzf.pcd.*binary_compressed is not supported"):
        read_pcd(tmp_path / "lzf.pcd")
    write_pcd(tmp_path / "short.pcd", np.zeros((4, 3)), binary=True)
    data = (tmp_path / "short.pcd").read_bytes()
    (tmp_path / "short.pcd").write_bytes(data[:-5])
    with pytest.raises(PointCloudError, match="short.pcd.*DATA binary holds"):
        read_pcd(tmp_path / "short.pcd")
    (tmp_path / "x.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n"
    )
    with pytest.raises(PointCloudError, match="x.ply.*no property 'y'"):
        read_ply(tmp_path / "x.ply")
    with pytest.raises(ValueError, match="unknown point-cloud suffix"):
        write_points(tmp_path / "a.xyz", np.zeros((1, 3)))
    with pytest.raises(ValueError, match="shape \\(N, 3\\)"):
        write_ply(tmp_path / "a.ply", np.zeros((2, 2)))
