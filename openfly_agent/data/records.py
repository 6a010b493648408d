"""Annotation records (one JSON object per trajectory) <-> `Episode`, with field-by-field validation.

Release fields (docs/OFFICIAL_OPENFLY.md 1.2): `image_path`, `gpt_instruction`, `action`, `index_list`,
`pos` (3 numbers, sometimes a 4th = yaw), `yaw`. Our extra fields: `scene_id`, `split`, `category`,
`pitch_deg`, `landmark_ids`, `boxes` ((cx, cy, w, h) or null per frame), `box_visible`, `goal`, `leg_goals`
(the goal of each leg of a chained route, in order).
"""

from __future__ import annotations

import math
from collections import Counter
from numbers import Real

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode, SchemaError

RELEASE_FIELDS = ("image_path", "gpt_instruction", "action", "index_list", "pos", "yaw")
PER_FRAME_FIELDS = ("action", "index_list", "pos", "yaw")  # one entry per kept frame each
YAW_MATCH_TOL_RAD = 1e-6  # a 4th `pos` number must equal `yaw` (mod 2 pi) within this


def parse_episode_id(episode_id: str, file: str = "", record: int | str = "") -> tuple[str, str]:
    """`<scene>/astar_data/<category>/<folder>` -> (scene_id, category); category "" for other layouts.

    Raises:
        SchemaError: the id is empty, absolute, has backslashes or `..` parts.
    """
    parts = episode_id.split("/")
    if not episode_id or episode_id.startswith("/") or "\\" in episode_id or ".." in parts or "" in parts:
        raise SchemaError(
            file, record, "image_path", f"not a relative '<scene>/.../<folder>' path: {episode_id!r}"
        )
    category = parts[2] if len(parts) >= 4 and parts[1] == "astar_data" else ""
    return parts[0], category


def pitch_for_category(category: str) -> float:
    """Camera pitch of a trajectory: -45 deg for `high_*` categories, else 0 (docs/CONVENTIONS.md, "Camera")."""
    return C.HIGH_CATEGORY_PITCH_DEG if category.startswith("high") else 0.0


def _is_number(value) -> bool:
    return isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)


def _list_field(record: dict, name: str, file: str, index: int) -> list:
    value = record.get(name)
    if not isinstance(value, list):
        raise SchemaError(file, index, name, f"expected a list, got {type(value).__name__}")
    return value


def _parse_actions(record: dict, file: str, index: int) -> np.ndarray:
    values = _list_field(record, "action", file, index)
    for t, a in enumerate(values):
        if not isinstance(a, int) or isinstance(a, bool):
            raise SchemaError(file, index, "action", f"entry {t} is {a!r}, expected an integer id")
        if a not in C.ACTION_NAMES:
            raise SchemaError(
                file, index, "action", f"entry {t} is {a}, not a known action id {C.ALL_ACTION_IDS}"
            )
    if not values:
        raise SchemaError(file, index, "action", "empty")
    return np.asarray(values, dtype=np.int64)


def _frame_count(record: dict, file: str, index: int) -> int:
    """The number of kept frames: the length most per-frame lists share (the action list's on a tie).

    Raises:
        SchemaError: naming the list whose length differs (an `action` one entry too long is `action`'s error,
            not `index_list`'s).
    """
    lengths = {name: len(_list_field(record, name, file, index)) for name in PER_FRAME_FIELDS}
    shared = Counter(lengths.values())
    n = max(shared, key=lambda length: (shared[length], length == lengths["action"]))
    for name, length in lengths.items():
        if length != n:
            agree = ", ".join(other for other, other_length in lengths.items() if other_length == n)
            raise SchemaError(file, index, name, f"length {length} != {n} frames ({agree}: {n} entries)")
    return n


def four_number_positions(record: dict) -> int:
    """How many `pos` entries of a (valid) record carry a 4th number, the yaw the reader drops."""
    return sum(isinstance(p, list) and len(p) == 4 for p in record.get("pos") or [])


def _parse_poses(record: dict, n: int, file: str, index: int) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) positions and (T,) yaws of a record whose lists hold `n` entries each; a 4th `pos` number is
    checked against `yaw` and dropped."""
    pos, yaw = record["pos"], record["yaw"]
    for t, y in enumerate(yaw):
        if not _is_number(y):
            raise SchemaError(file, index, "yaw", f"entry {t} is {y!r}, expected a finite number")
    positions = np.empty((n, 3), dtype=np.float64)
    for t, p in enumerate(pos):
        if not isinstance(p, list) or len(p) not in (3, 4) or not all(_is_number(v) for v in p):
            raise SchemaError(file, index, "pos", f"entry {t} is {p!r}, expected 3 or 4 finite numbers")
        if len(p) == 4 and abs(math.remainder(p[3] - yaw[t], 2.0 * math.pi)) > YAW_MATCH_TOL_RAD:
            raise SchemaError(file, index, "pos", f"entry {t}: 4th number {p[3]} is not yaw[{t}] = {yaw[t]}")
        positions[t] = p[:3]
    return positions, np.asarray(yaw, dtype=np.float64)


def _parse_boxes(record: dict, n: int, file: str, index: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Our `boxes` / `box_visible` fields: (T, 4) with zeros where not visible, (T,) bool; None if absent."""
    if "boxes" not in record and "box_visible" not in record:
        return None, None
    raw_boxes = _list_field(record, "boxes", file, index)
    raw_visible = _list_field(record, "box_visible", file, index)
    for name, value in (("boxes", raw_boxes), ("box_visible", raw_visible)):
        if len(value) != n:
            raise SchemaError(file, index, name, f"length {len(value)} != {n} actions")
    boxes, visible = np.zeros((n, 4), dtype=np.float64), np.zeros(n, dtype=bool)
    for t, (box, vis) in enumerate(zip(raw_boxes, raw_visible)):
        if not isinstance(vis, bool):
            raise SchemaError(file, index, "box_visible", f"entry {t} is {vis!r}, expected true/false")
        if vis:
            boxes[t] = check_box(box, file, index, f"boxes[{t}]")
        elif box is not None:
            raise SchemaError(
                file, index, "boxes", f"entry {t} is not visible, so it must be null, got {box!r}"
            )
        visible[t] = vis
    return boxes, visible


def check_box(box, file: str, record: int | str, name: str) -> np.ndarray:
    """A visible box: 4 finite numbers (cx, cy, w, h) with centre in [0, 1] and 0 < w, h <= 1."""
    if not isinstance(box, (list, tuple, np.ndarray)) or len(box) != 4 or not all(_is_number(v) for v in box):
        raise SchemaError(file, record, name, f"expected 4 finite numbers (cx, cy, w, h), got {box!r}")
    cx, cy, w, h = (float(v) for v in box)
    if not (0.0 <= cx <= 1.0 and 0.0 <= cy <= 1.0 and 0.0 < w <= 1.0 and 0.0 < h <= 1.0):
        raise SchemaError(file, record, name, f"box {box!r} is outside [0, 1] or empty")
    return np.array([cx, cy, w, h], dtype=np.float64)


def _string_field(record: dict, name: str, file: str, index: int, default: str | None = None) -> str | None:
    value = record.get(name, default)
    if value is not None and not isinstance(value, str):
        raise SchemaError(file, index, name, f"expected a string, got {type(value).__name__}")
    return value


def episode_from_record(record: dict, file: str = "", index: int = 0, split: str | None = None) -> Episode:
    """Build an `Episode` from one annotation record, labels exactly as stored (no reader options).

    Args:
        record: a dict in the release format, optionally with our extra fields.
        file, index: where the record came from (used in error messages).
        split: split to assign when the record has no `split` field.

    Raises:
        SchemaError: naming `file`, `index` and the field that breaks the schema.
    """
    if not isinstance(record, dict):
        raise SchemaError(file, index, "<record>", f"expected a JSON object, got {type(record).__name__}")
    missing = [name for name in RELEASE_FIELDS if name not in record]
    if missing:
        raise SchemaError(file, index, missing[0], f"missing (record has {sorted(record)})")
    episode_id = _string_field(record, "image_path", file, index)
    scene_id, category = parse_episode_id(episode_id, file, index)
    if record.get("scene_id", scene_id) != scene_id:
        raise SchemaError(file, index, "scene_id", f"{record['scene_id']!r} != first part of {episode_id!r}")
    instruction = _string_field(record, "gpt_instruction", file, index)
    actions = _parse_actions(record, file, index)
    n = _frame_count(record, file, index)
    frame_ids = record["index_list"]
    for t, frame_id in enumerate(frame_ids):
        if not isinstance(frame_id, str) or not frame_id:
            raise SchemaError(
                file, index, "index_list", f"entry {t} is {frame_id!r}, expected a non-empty string"
            )
    positions, yaws = _parse_poses(record, n, file, index)
    boxes, visible = _parse_boxes(record, n, file, index)
    landmark_ids = record.get("landmark_ids", [])
    if not isinstance(landmark_ids, list) or not all(isinstance(x, str) for x in landmark_ids):
        raise SchemaError(file, index, "landmark_ids", f"expected a list of strings, got {landmark_ids!r}")
    record_split = _string_field(record, "split", file, index, split)
    if record_split is not None and record_split not in C.SPLITS:
        raise SchemaError(file, index, "split", f"{record_split!r} is not one of {C.SPLITS}")
    goal = record.get("goal")
    if goal is not None and (not isinstance(goal, list) or len(goal) != 3 or not all(map(_is_number, goal))):
        raise SchemaError(file, index, "goal", f"expected 3 finite numbers, got {goal!r}")
    leg_goals = record.get("leg_goals")
    if leg_goals is not None and (
        not isinstance(leg_goals, list)
        or not leg_goals
        or not all(isinstance(g, list) and len(g) == 3 and all(map(_is_number, g)) for g in leg_goals)
    ):
        raise SchemaError(
            file, index, "leg_goals", f"expected a list of 3 finite numbers per leg, got {leg_goals!r}"
        )
    if leg_goals is not None and landmark_ids and len(leg_goals) != len(landmark_ids):
        raise SchemaError(
            file,
            index,
            "leg_goals",
            f"{len(leg_goals)} legs for {len(landmark_ids)} landmark_ids: one goal per target",
        )
    category = _string_field(record, "category", file, index, category)
    pitch = record.get("pitch_deg", pitch_for_category(category))
    if not _is_number(pitch):
        raise SchemaError(file, index, "pitch_deg", f"expected a number, got {pitch!r}")
    return Episode(
        episode_id=episode_id,
        scene_id=scene_id,
        instruction=instruction,
        actions=actions,
        positions=positions,
        yaws=yaws,
        frame_ids=list(frame_ids),
        split=record_split,
        category=category,
        pitch_deg=float(pitch),
        boxes=boxes,
        box_visible=visible,
        landmark_ids=list(landmark_ids),
        goal=None if goal is None else np.asarray(goal, dtype=np.float64),
        leg_goals=None if leg_goals is None else np.asarray(leg_goals, dtype=np.float64),
    )


def _boxes_to_json(boxes: np.ndarray | None, visible: np.ndarray | None) -> tuple[list, list] | None:
    if boxes is None:
        return None
    out = [[float(v) for v in box] if vis else None for box, vis in zip(boxes, visible)]
    return out, [bool(v) for v in visible]


def record_from_episode(episode: Episode) -> dict:
    """The annotation record of `episode`: release fields first, then our extras (JSON-ready)."""
    record = {
        "image_path": episode.episode_id,
        "gpt_instruction": episode.instruction,
        "action": [int(a) for a in episode.actions],
        "index_list": list(episode.frame_ids),
        "pos": [[float(v) for v in p] for p in episode.positions],
        "yaw": [float(y) for y in episode.yaws],
        "scene_id": episode.scene_id,
        "split": episode.split,
        "category": episode.category,
        "pitch_deg": float(episode.pitch_deg),
        "landmark_ids": list(episode.landmark_ids),
    }
    boxes = _boxes_to_json(episode.boxes, episode.box_visible)
    if boxes is not None:
        record["boxes"], record["box_visible"] = boxes
    if episode.goal is not None:
        record["goal"] = [float(v) for v in episode.goal]
    if episode.leg_goals is not None:
        record["leg_goals"] = [[float(v) for v in g] for g in episode.leg_goals]
    return record
