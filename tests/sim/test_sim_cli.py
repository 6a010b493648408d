"""The sim CLI writes a frame, a point cloud and a landmark list that read back."""

import json

import cv2
import pytest

from openfly_agent.sim.city import CityConfig, generate_city
from openfly_agent.sim.cli import main
from openfly_agent.sim.pointcloud import read_points


def test_export_landmarks_and_render(tmp_path, capsys):
    common = ["--seed=3", "--size_m=300"]
    assert main(["export", *common, f"--out={tmp_path / 'c.pcd'}", "--spacing=4"]) == 0
    city = generate_city(3, CityConfig(size_m=300.0))
    assert len(read_points(tmp_path / "c.pcd")) == len(city.point_cloud(4.0))
    assert main(["landmarks", *common, "--out", str(tmp_path / "l.jsonl")]) == 0
    records = [json.loads(line) for line in (tmp_path / "l.jsonl").read_text().splitlines()]
    assert [r["landmark_id"] for r in records] == [lm.landmark_id for lm in city.landmarks]
    assert records[0]["description"] == city.landmarks[0].description()
    argv = ["render", *common, "--pose=[-160,-160,60,0.8]", "--width=48", "--height=32", "--boxes"]
    assert main([*argv, f"--out={tmp_path / 'f.png'}"]) == 0
    assert cv2.imread(str(tmp_path / "f.png")).shape == (32, 48, 3)
    assert "landmark boxes" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["export", "--seed=1"], "--out is required"),
        (["export", "--size-m=300", "--out=x.ply"], "did you mean --size_m?"),
        (["render", "--pose=[1,2]", "--out=f.png"], "--pose takes 4 numbers"),
        (["render", "--width=wide", "--out=f.png"], "width"),
        (["paint"], "unknown command 'paint'"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and message in err, err
    assert not list(tmp_path.iterdir())  # nothing written
