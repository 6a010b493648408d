"""Per-trajectory parquet files in the OpenFly release schema (plus our extra columns), read and written.

Release columns (docs/OFFICIAL_OPENFLY.md 1.3): `image` struct {bytes: PNG, path}, `pos`, `yaw`,
`action_type` (str), `action_value` (m or deg), `env_id`, `traj_id`, `frame_index`, `image_id`.
Ours add `episode_id`, `scene_id`, `split`, `instruction`, `action` (id), `landmark_ids`, `box`
(null when not visible), `box_visible`. The Hugging Face `Image` feature is declared in the schema
metadata, so `datasets.load_dataset("parquet", ...)` decodes `image` without a loading script.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from openfly_agent import constants as C
from openfly_agent.data.records import check_box, parse_episode_id, pitch_for_category
from openfly_agent.data.schema import Episode, SchemaError
from openfly_agent.utils.files import write_atomic

# action_type strings of the release -> ids; "go straight" is resolved by its value (3 / 6 / 9 m).
ACTION_TYPE_IDS = {
    "stop": C.ACTION_STOP,
    "turn left": C.ACTION_TURN_LEFT,
    "turn right": C.ACTION_TURN_RIGHT,
    "go up": C.ACTION_ASCEND,
    "go down": C.ACTION_DESCEND,
    "move left": C.ACTION_MOVE_LEFT,
    "move right": C.ACTION_MOVE_RIGHT,
    "up": C.ACTION_TAKEOFF,
    "down": C.ACTION_LANDING,
    "donw": C.ACTION_LANDING,  # a typo seen in released files (docs/OFFICIAL_OPENFLY.md 1.3)
}
GO_STRAIGHT = "go straight"
STRAIGHT_IDS = {3: C.ACTION_FORWARD, 6: C.ACTION_FORWARD_6, 9: C.ACTION_FORWARD_9}
# id -> (action_type, action_value) as written by us (the release vocabulary).
ACTION_TYPE_OF_ID = {
    C.ACTION_STOP: ("stop", 0),
    C.ACTION_FORWARD: (GO_STRAIGHT, 3),
    C.ACTION_FORWARD_6: (GO_STRAIGHT, 6),
    C.ACTION_FORWARD_9: (GO_STRAIGHT, 9),
    C.ACTION_TURN_LEFT: ("turn left", 30),
    C.ACTION_TURN_RIGHT: ("turn right", 30),
    C.ACTION_ASCEND: ("go up", 3),
    C.ACTION_DESCEND: ("go down", 3),
    C.ACTION_MOVE_LEFT: ("move left", 3),
    C.ACTION_MOVE_RIGHT: ("move right", 3),
    C.ACTION_TAKEOFF: ("up", 3),
    C.ACTION_LANDING: ("down", 3),
}
IMAGE_COLUMN = "image"
FRAME_KEY_COLUMNS = ("image", "image_id", "frame_index")  # enough to match rows to `index_list` stems
_STEM_RE = re.compile(r"^(.*)_(\d+)$")

RELEASE_FIELDS = [
    pa.field("image", pa.struct([pa.field("bytes", pa.binary()), pa.field("path", pa.string())])),
    pa.field("pos", pa.list_(pa.float64())),
    pa.field("yaw", pa.float64()),
    pa.field("action_type", pa.string()),
    pa.field("action_value", pa.int64()),
    pa.field("env_id", pa.string()),
    pa.field("traj_id", pa.string()),
    pa.field("frame_index", pa.int64()),
    pa.field("image_id", pa.string()),
]
EXTRA_FIELDS = [
    pa.field("episode_id", pa.string()),
    pa.field("scene_id", pa.string()),
    pa.field("split", pa.string()),
    pa.field("instruction", pa.string()),
    pa.field("action", pa.int64()),
    pa.field("landmark_ids", pa.list_(pa.string())),
    pa.field("box", pa.list_(pa.float64(), 4)),
    pa.field("box_visible", pa.bool_()),
]
# Hugging Face `datasets` feature declarations for the same columns (schema metadata key "huggingface").
_HF_FEATURES = {
    "image": {"_type": "Image"},
    "pos": {"feature": {"dtype": "float64", "_type": "Value"}, "_type": "List"},
    "yaw": {"dtype": "float64", "_type": "Value"},
    "action_type": {"dtype": "string", "_type": "Value"},
    "action_value": {"dtype": "int64", "_type": "Value"},
    "env_id": {"dtype": "string", "_type": "Value"},
    "traj_id": {"dtype": "string", "_type": "Value"},
    "frame_index": {"dtype": "int64", "_type": "Value"},
    "image_id": {"dtype": "string", "_type": "Value"},
    "episode_id": {"dtype": "string", "_type": "Value"},
    "scene_id": {"dtype": "string", "_type": "Value"},
    "split": {"dtype": "string", "_type": "Value"},
    "instruction": {"dtype": "string", "_type": "Value"},
    "action": {"dtype": "int64", "_type": "Value"},
    "landmark_ids": {"feature": {"dtype": "string", "_type": "Value"}, "_type": "List"},
    "box": {"feature": {"dtype": "float64", "_type": "Value"}, "length": 4, "_type": "List"},
    "box_visible": {"dtype": "bool", "_type": "Value"},
}
TRAJECTORY_SCHEMA = pa.schema(
    RELEASE_FIELDS + EXTRA_FIELDS,
    metadata={"huggingface": json.dumps({"info": {"features": _HF_FEATURES}})},
)


def split_frame_id(frame_id: str, t: int) -> tuple[str, int]:
    """`20250109_131812_2` -> ("20250109_131812", 2) as the release stores it; other ids -> (id, t)."""
    match = _STEM_RE.match(frame_id)
    return (match.group(1), int(match.group(2))) if match else (frame_id, t)


def trajectory_table(episode: Episode, encoded_frames: list[bytes], image_ext: str) -> pa.Table:
    """One row per kept frame of `episode`, in TRAJECTORY_SCHEMA; visible boxes must be valid."""
    n = len(episode)
    env_id, _, traj_id = episode.episode_id.rpartition("/")
    keys = [split_frame_id(f, t) for t, f in enumerate(episode.frame_ids)]
    types = [ACTION_TYPE_OF_ID[int(a)] for a in episode.actions]
    if episode.boxes is None:
        boxes, visible = [None] * n, [False] * n
    else:
        visible = [bool(v) for v in episode.box_visible]
        boxes = [
            [float(x) for x in check_box(b, episode.episode_id, t, "boxes")] if v else None
            for t, (b, v) in enumerate(zip(episode.boxes, visible))
        ]
    columns = {
        "image": [
            {"bytes": b, "path": f"{f}.{image_ext}"} for b, f in zip(encoded_frames, episode.frame_ids)
        ],
        "pos": [[float(v) for v in p] for p in episode.positions],
        "yaw": [float(y) for y in episode.yaws],
        "action_type": [t for t, _ in types],
        "action_value": [v for _, v in types],
        "env_id": [env_id] * n,
        "traj_id": [traj_id] * n,
        "frame_index": [k for _, k in keys],
        "image_id": [i for i, _ in keys],
        "episode_id": [episode.episode_id] * n,
        "scene_id": [episode.scene_id] * n,
        "split": [episode.split] * n,
        "instruction": [episode.instruction] * n,
        "action": [int(a) for a in episode.actions],
        "landmark_ids": [list(episode.landmark_ids)] * n,
        "box": boxes,
        "box_visible": visible,
    }
    return pa.table(columns, schema=TRAJECTORY_SCHEMA)


def _row_action(row: dict, path: str, r: int) -> int:
    if row.get("action") is not None:
        action = int(row["action"])
        if action not in C.ACTION_NAMES:
            raise SchemaError(path, r, "action", f"unknown action id {action}")
        return action
    kind = row.get("action_type")
    kind = kind.strip().lower() if isinstance(kind, str) else kind
    if kind == GO_STRAIGHT:
        value = row.get("action_value")
        if value is None or not math.isfinite(float(value)) or round(float(value)) not in STRAIGHT_IDS:
            raise SchemaError(path, r, "action_value", f"'go straight' needs 3, 6 or 9 m, got {value!r}")
        return STRAIGHT_IDS[round(float(value))]
    if kind not in ACTION_TYPE_IDS:
        raise SchemaError(path, r, "action_type", f"unknown action type {kind!r}")
    return ACTION_TYPE_IDS[kind]


def _row_pose(row: dict, path: str, r: int) -> tuple[list[float], float]:
    pos, yaw = row.get("pos"), row.get("yaw")
    if pos is None or len(pos) not in (3, 4) or not all(v is not None and math.isfinite(v) for v in pos):
        raise SchemaError(path, r, "pos", f"expected 3 or 4 finite numbers, got {pos!r}")
    if yaw is None or not math.isfinite(yaw):
        raise SchemaError(path, r, "yaw", f"expected a finite number, got {yaw!r}")
    return list(pos[:3]), float(yaw)


def exact_frame_key(row: dict) -> str | None:
    """`<image_id>_<frame_index>`: the key that names one row alone (the release gives the raw rows of a merged
    forward move one shared image path, never one shared frame index); None without those columns."""
    if row.get("image_id") is None or row.get("frame_index") is None:
        return None
    return f"{row['image_id']}_{int(row['frame_index'])}"


def row_frame_keys(row: dict) -> list[str]:
    """Names under which a parquet row may appear in `index_list`, most specific first.

    The image path's stem, `<image_id>_<frame_index>`, and `image_id` alone (in case it already ends in
    `_<k>`); empty when the row has none of these columns.
    """
    keys = []
    image = row.get("image") or {}
    if image.get("path"):
        keys.append(Path(str(image["path"]).replace("\\", "/")).stem)
    if exact_frame_key(row) is not None:
        keys.append(exact_frame_key(row))
    if row.get("image_id") is not None:
        keys.append(str(row["image_id"]))
    return keys


def read_parquet_episode(path: str | Path, instruction: str | None = None) -> Episode:
    """An `Episode` from one trajectory parquet (release or ours), labels as stored; images are not read.

    The episode id is `env_id + "/" + traj_id` (backslashes normalised), as the release joins parquet to
    the annotation's `image_path`. The instruction comes from our `instruction` column, or `instruction`.

    Raises:
        SchemaError: naming the parquet file, the row and the column.
    """
    path = str(path)
    columns = [n for n in pq.read_schema(path).names if n != IMAGE_COLUMN]
    rows = pq.read_table(path, columns=columns).to_pylist()
    if not rows:
        raise SchemaError(path, 0, "<rows>", "the trajectory has no rows")
    for name in ("env_id", "traj_id"):
        if not isinstance(rows[0].get(name), str) or not rows[0][name]:
            raise SchemaError(path, 0, name, f"missing or empty: {rows[0].get(name)!r}")
    episode_id = rows[0]["env_id"].replace("\\", "/").strip("/") + "/" + rows[0]["traj_id"]
    scene_id, category = parse_episode_id(episode_id, path, 0)
    actions, positions, yaws, frame_ids = [], [], [], []
    for r, row in enumerate(rows):
        actions.append(_row_action(row, path, r))
        pos, yaw = _row_pose(row, path, r)
        positions.append(pos)
        yaws.append(yaw)
        frame_ids.append((row_frame_keys(row) or [str(r)])[0])
    boxes = visible = None
    if "box_visible" in rows[0]:
        visible = np.array([bool(row["box_visible"]) for row in rows])
        boxes = np.zeros((len(rows), 4))
        for r, row in enumerate(rows):
            if visible[r]:
                boxes[r] = check_box(row.get("box"), path, r, "box")
    first = rows[0]
    return Episode(
        episode_id=episode_id,
        scene_id=scene_id,
        instruction=first.get("instruction") or instruction or "",
        actions=np.asarray(actions),
        positions=np.asarray(positions),
        yaws=np.asarray(yaws),
        frame_ids=frame_ids,
        split=first.get("split"),
        category=category,
        pitch_deg=pitch_for_category(category),
        boxes=boxes,
        box_visible=visible,
        landmark_ids=list(first.get("landmark_ids") or []),
    )


def write_table_atomic(table: pa.Table, path: Path) -> None:
    """Write `table` to `path` through a temporary file and a rename (no half-written parquet)."""
    write_atomic(path, lambda tmp: pq.write_table(table, tmp))
