"""Release-schema trajectory parquet written by the test (PNG bytes in an `image` struct), read back."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from data_factories import make_frames

from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.frames import FrameStore
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.data.parquet_io import read_parquet_episode
from openfly_agent.data.schema import SchemaError

ENV_ID = "env_airsim_18\\astar_data\\low_short_updown"  # the release sometimes has Windows separators
TRAJ_ID = "2025-1-19_7-4-57_654899"
EPISODE_ID = "env_airsim_18/astar_data/low_short_updown/" + TRAJ_ID
# One row per RAW frame: raw frames 3 and 4 were merged into the 6 m block kept at raw frame 4 ... so the
# annotation keeps raw frames 0, 1, 2, 4, 5, 6 (not 3).
RAW_ROWS = [  # (action_type, action_value, pos, yaw)
    ("up", 3, [1.0, 2.0, 0.0], 0.5),
    ("up", 3, [1.0, 2.0, 3.0, 0.5], 0.5),  # a 4th pos number, as some released entries have
    ("go straight", 3, [1.0, 2.0, 6.0], 0.5),
    ("go straight", 3, [3.6, 3.4, 6.0], 0.5),
    ("go straight", 6, [6.3, 4.9, 6.0], 0.5),
    ("stop", 0, [8.9, 6.3, 6.0], 0.5),
    ("donw", 3, [8.9, 6.3, 3.0], 0.5),  # the typo seen in released files
]
KEPT = [0, 1, 2, 4, 5, 6]


def _png(rgb: np.ndarray) -> bytes:
    return cv2.imencode(".png", rgb[..., ::-1])[1].tobytes()


def write_release_parquet(
    path: Path,
    frames: list[np.ndarray],
    corrupt_row: int | None = None,
    stem_in_image_id: bool = False,
    path_of_row: dict[int, int] | None = None,
) -> None:
    """Columns and types as in the released files (docs/OFFICIAL_OPENFLY.md 1.3); no extra columns.

    `stem_in_image_id`: no image path, and `image_id` already holds the whole `<stamp>_<k>` stem.
    `path_of_row`: row -> the raw index its image path names instead of its own (rows sharing a path).
    """
    stamp = "20250119_070457"
    named = {k: (path_of_row or {}).get(k, k) for k in range(len(frames))}
    image = [{"bytes": _png(f), "path": f"{stamp}_{named[k]}.png"} for k, f in enumerate(frames)]
    if stem_in_image_id:
        image = [{"bytes": i["bytes"], "path": None} for i in image]
    if corrupt_row is not None:
        image[corrupt_row]["bytes"] = image[corrupt_row]["bytes"][:40]
    table = pa.table(
        {
            "image": image,
            "pos": [row[2] for row in RAW_ROWS],
            "yaw": [row[3] for row in RAW_ROWS],
            "action_type": [row[0] for row in RAW_ROWS],
            "action_value": [row[1] for row in RAW_ROWS],
            "env_id": [ENV_ID] * len(RAW_ROWS),
            "traj_id": [TRAJ_ID] * len(RAW_ROWS),
            "frame_index": list(range(len(RAW_ROWS))),
            "image_id": [f"{stamp}_{k}" if stem_in_image_id else stamp for k in range(len(RAW_ROWS))],
        }
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path)


def _annotation(root: Path) -> None:
    record = {
        "image_path": EPISODE_ID,
        "gpt_instruction": "Take off, fly ahead and land.",
        "action": [-1, -1, 1, 8, 0, -2],
        "index_list": [f"20250119_070457_{k}" for k in KEPT],
        "pos": [RAW_ROWS[k][2] for k in KEPT],
        "yaw": [RAW_ROWS[k][3] for k in KEPT],
    }
    (root / "Annotation").mkdir(parents=True)
    (root / "Annotation" / "train.json").write_text(json.dumps([record]))


@pytest.mark.parametrize(
    ("file_name", "stem_in_image_id"),
    [(TRAJ_ID, False), ("2025-01-19_07-04-57_654899", False), (TRAJ_ID, True)],
)
def test_release_parquet_frames_are_pixel_exact(tmp_path, file_name, stem_in_image_id):
    frames = make_frames(len(RAW_ROWS), height=10, width=14, seed=4)
    folder = tmp_path / "traj" / "env_airsim_18/astar_data/low_short_updown"
    write_release_parquet(folder / f"{file_name}.parquet", frames, stem_in_image_id=stem_in_image_id)
    _annotation(tmp_path)
    episode = load_openfly_dataset(tmp_path, "train", ReaderOptions(takeoff_landing="keep"))[0]
    store = FrameStore(tmp_path)
    got = store.frames(episode)
    assert len(got) == len(KEPT)
    for rgb, k in zip(got, KEPT):
        assert rgb.dtype == np.uint8 and rgb.shape == (10, 14, 3)
        np.testing.assert_array_equal(rgb, frames[k])
    np.testing.assert_array_equal(store.frame(episode, 3), frames[4])


def test_rows_sharing_an_image_path_give_each_kept_frame_its_own_row(tmp_path, caplog):
    """Raw rows 2, 3, 4 (the merged move) all name `..._4.png`: kept frame `20250119_070457_4` is row 4's
    (`image_id` + `frame_index` 4), not row 2's, 6 m behind; one warning per trajectory, with the counts."""
    frames = make_frames(len(RAW_ROWS), seed=5)
    folder = tmp_path / "traj" / "env_airsim_18/astar_data/low_short_updown"
    write_release_parquet(folder / f"{TRAJ_ID}.parquet", frames, path_of_row={2: 4, 3: 4})
    _annotation(tmp_path)
    episode = load_openfly_dataset(tmp_path, "train", ReaderOptions(takeoff_landing="keep"))[0]
    store = FrameStore(tmp_path, cache_episodes=1, cache_frames=1)
    with caplog.at_level("WARNING", logger="openfly_agent.data.frames"):
        got = store.frames(episode)
        store._reset_caches()  # a cache miss reads the file again: no second warning
        store.frame(episode, 3)
    for rgb, k in zip(got, KEPT):
        np.testing.assert_array_equal(rgb, frames[k])
    # `..._4` is the path stem of rows 2, 3, 4 and the exact key of row 4; `..._2` is row 2's exact key only
    [warning] = [r.getMessage() for r in caplog.records]
    assert warning.startswith(
        f"{folder / TRAJ_ID}.parquet: 1 of 6 kept frames are named by more than one row"
    )
    assert warning.endswith("'20250119_070457_4': rows [2, 3, 4], took row 4")


def test_release_parquet_episode_fields(tmp_path):
    path = tmp_path / "t.parquet"
    write_release_parquet(path, make_frames(len(RAW_ROWS)))
    episode = read_parquet_episode(path, instruction="go")
    assert episode.episode_id == EPISODE_ID and episode.scene_id == "env_airsim_18"
    assert episode.category == "low_short_updown" and episode.instruction == "go"
    assert episode.actions.tolist() == [-1, -1, 1, 1, 8, 0, -2]
    assert episode.frame_ids == [f"20250119_070457_{k}" for k in range(7)]
    np.testing.assert_array_equal(episode.positions, [row[2][:3] for row in RAW_ROWS])
    np.testing.assert_array_equal(episode.yaws, [0.5] * 7)
    assert episode.boxes is None


def test_corrupt_png_names_parquet_row_and_image(tmp_path):
    path = tmp_path / "traj" / "env_airsim_18/astar_data/low_short_updown" / f"{TRAJ_ID}.parquet"
    write_release_parquet(path, make_frames(len(RAW_ROWS)), corrupt_row=4)
    _annotation(tmp_path)
    episode = load_openfly_dataset(tmp_path, "train", ReaderOptions(takeoff_landing="keep"))[0]
    store = FrameStore(tmp_path)
    np.testing.assert_array_equal(store.frame(episode, 0).shape, (12, 16, 3))
    with pytest.raises(SchemaError) as info:
        store.frame(episode, 3)  # kept frame 3 = raw row 4
    assert (info.value.file, info.value.record, info.value.field_name) == (str(path), 4, "image")


def test_bad_parquet_rows_name_row_and_column(tmp_path):
    path = tmp_path / "t.parquet"
    write_release_parquet(path, make_frames(len(RAW_ROWS)))
    table = pq.read_table(path)
    kinds = table.column("action_type").to_pylist()
    kinds[2] = "hover"
    pq.write_table(table.set_column(3, "action_type", pa.array(kinds)), path)
    with pytest.raises(SchemaError) as info:
        read_parquet_episode(path)
    assert (info.value.record, info.value.field_name) == (2, "action_type")
    values = table.column("action_value").to_pylist()
    values[3] = 12
    pq.write_table(table.set_column(4, "action_value", pa.array(values)), path)
    with pytest.raises(SchemaError) as info:
        read_parquet_episode(path)
    assert (info.value.record, info.value.field_name) == (3, "action_value")


def test_missing_frame_row_and_missing_frames(tmp_path):
    path = tmp_path / "traj" / "env_airsim_18/astar_data/low_short_updown" / f"{TRAJ_ID}.parquet"
    write_release_parquet(path, make_frames(len(RAW_ROWS)))
    _annotation(tmp_path)
    episode = load_openfly_dataset(tmp_path, "train", ReaderOptions(takeoff_landing="keep"))[0]
    episode.frame_ids[2] = "20250119_070457_99"
    with pytest.raises(SchemaError, match="no row holds frame 2"):
        FrameStore(tmp_path).frame(episode, 0)
    episode.episode_id = "env_airsim_18/astar_data/low_short_updown/other"
    with pytest.raises(FileNotFoundError, match="no frames for episode"):
        FrameStore(tmp_path).frame(episode, 0)


def test_image_folder_frames(tmp_path):
    frames = make_frames(len(RAW_ROWS), seed=2)
    _annotation(tmp_path)
    episode = load_openfly_dataset(tmp_path, "train", ReaderOptions(takeoff_landing="keep"))[0]
    folder = tmp_path / "images" / EPISODE_ID
    folder.mkdir(parents=True)
    for frame_id, k in zip(episode.frame_ids, KEPT):
        (folder / f"{frame_id}.png").write_bytes(_png(frames[k]))
    got = FrameStore(tmp_path).frames(episode)
    for rgb, k in zip(got, KEPT):
        np.testing.assert_array_equal(rgb, frames[k])
