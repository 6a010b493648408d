"""The in-memory episode: one trajectory with its instruction, in the OpenFly annotation's terms.

Readers (released OpenFly JSON / parquet) and the toolchain's writer both go through `Episode`, so
training and evaluation see one schema whatever the source. Frames are referenced, not held: a
`FrameSource` (data/frames.py) resolves `frame_ids` to RGB arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class SchemaError(ValueError):
    """A record that breaks the schema; the message names the file, the record and the field."""

    def __init__(self, file: str, record: int | str, field_name: str, problem: str):
        self.file, self.record, self.field_name, self.problem = str(file), record, field_name, problem
        super().__init__(f"{file}: record {record}: field '{field_name}': {problem}")


@dataclass
class Episode:
    """One trajectory. Arrays are indexed by kept frame t = 0..T-1; `actions[t]` is taken at frame t.

    Attributes mirror the OpenFly annotation record (docs/OFFICIAL_OPENFLY.md section 1.2) plus our extras.
    """

    episode_id: str  # OpenFly `image_path`, e.g. "env_airsim_16/astar_data/medium_average/<folder>"
    scene_id: str  # first path component, e.g. "env_airsim_16" or "embedded-17"
    instruction: str  # `gpt_instruction`
    actions: np.ndarray  # (T,) int64, ids -2..9
    positions: np.ndarray  # (T, 3) float64 metres
    yaws: np.ndarray  # (T,) float64 radians, CCW from +x, NOT wrapped (as released)
    frame_ids: list[str]  # `index_list`, image stems
    split: str | None = None  # train / test_seen / test_unseen
    category: str = ""  # e.g. "high_short", "medium_average_updown"
    pitch_deg: float = 0.0  # camera pitch; -45 for `high_*` categories
    # Our extra columns (generated data; None for released data)
    boxes: np.ndarray | None = None  # (T, 4) (cx, cy, w, h) in [0, 1] of the target landmark
    box_visible: np.ndarray | None = None  # (T,) bool
    landmark_ids: list[str] = field(default_factory=list)  # target landmark(s), in route order
    goal: np.ndarray | None = None  # (3,) metres; default the last position (official evaluation)
    # (K, 3) metres: the goal of each leg of the planned route, in order (the last is `goal`); a DAgger expert
    # re-plans through them. None where unknown (released data, datasets generated before this field)
    leg_goals: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.actions = np.asarray(self.actions, dtype=np.int64)
        self.positions = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)
        self.yaws = np.asarray(self.yaws, dtype=np.float64)
        n = len(self.actions)
        for name, value in (
            ("positions", self.positions),
            ("yaws", self.yaws),
            ("frame_ids", self.frame_ids),
        ):
            if len(value) != n:
                raise SchemaError(
                    self.episode_id, self.episode_id, name, f"length {len(value)} != {n} actions"
                )
        if self.boxes is not None or self.box_visible is not None:
            self._check_boxes(n)
        if self.goal is None and n:
            self.goal = self.positions[-1].copy()
        if self.leg_goals is not None:
            self._check_leg_goals()

    def _check_boxes(self, n: int) -> None:
        """Boxes and visibility come together, one per frame: boxes (T, 4), box_visible (T,) bool."""
        if self.boxes is None or self.box_visible is None:
            missing = "boxes" if self.boxes is None else "box_visible"
            raise SchemaError(self.episode_id, self.episode_id, missing, "boxes and box_visible go together")
        self.boxes = np.asarray(self.boxes, dtype=np.float64)
        self.box_visible = np.asarray(self.box_visible, dtype=bool)
        if self.boxes.shape != (n, 4):
            raise SchemaError(
                self.episode_id, self.episode_id, "boxes", f"shape {self.boxes.shape} != ({n}, 4)"
            )
        if self.box_visible.shape != (n,):
            raise SchemaError(
                self.episode_id, self.episode_id, "box_visible", f"shape {self.box_visible.shape} != ({n},)"
            )

    def _check_leg_goals(self) -> None:
        """(K, 3) finite, K >= 1, one leg per target landmark when those are known."""
        self.leg_goals = np.asarray(self.leg_goals, dtype=np.float64)
        if self.leg_goals.ndim != 2 or self.leg_goals.shape[1:] != (3,) or not len(self.leg_goals):
            raise SchemaError(
                self.episode_id, self.episode_id, "leg_goals", f"shape {self.leg_goals.shape} != (K >= 1, 3)"
            )
        if not np.isfinite(self.leg_goals).all():
            raise SchemaError(self.episode_id, self.episode_id, "leg_goals", "not all finite")
        if self.landmark_ids and len(self.landmark_ids) != len(self.leg_goals):
            raise SchemaError(
                self.episode_id,
                self.episode_id,
                "leg_goals",
                f"{len(self.leg_goals)} legs for {len(self.landmark_ids)} target landmarks: one goal per target",
            )

    @property
    def route_goals(self) -> list[np.ndarray]:
        """The goals an expert flies through, in order: `leg_goals` where known, else [`goal`]."""
        if self.leg_goals is not None:
            return [np.asarray(g, dtype=np.float64) for g in self.leg_goals]
        return [np.asarray(self.goal, dtype=np.float64).reshape(3)]

    @property
    def has_boxes(self) -> bool:
        """Whether landmark boxes are known (generated data); released OpenFly data has none."""
        return self.boxes is not None

    def __len__(self) -> int:
        return len(self.actions)

    @property
    def poses(self) -> np.ndarray:
        """(T, 4) (x, y, z, yaw)."""
        return np.concatenate([self.positions, self.yaws[:, None]], axis=1)
