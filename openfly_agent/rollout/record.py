"""What happened in one closed-loop episode: the record the lockstep runner fills and the evaluation log stores."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from openfly_agent.utils.errors import RecordError

END_REASONS = ("stop", "max_steps", "collision", "error", "teleport")
RECORD_VERSION = 2  # 2 added `metrics`; rows of version 1 read with it empty


@dataclass
class EpisodeRecord:
    """What happened in one closed-loop episode.

    `poses[k]` is the pose after `k` actions (`poses[0]` = start), so `len(poses) == len(actions) + 1`;
    STOP leaves the pose unchanged. `collision_steps` are the steps whose motion hit occupied space.
    `boxes[k]` is the landmark box the policy predicted at step k (None: predicted invisible, or a policy
    without boxes); `keyframes[k]` the frame indices of the keyframe sets in its memory after step k.
    `metrics` is what the evaluation scored as it wrote the record, per metric profile: {profile: {"success",
    "ne", "oracle_success", "spl", "outcome"}} (empty: not scored, e.g. an engine error or an older log); for
    reading the log only, every table is recomputed from the trajectory.
    """

    split: str
    episode_id: str
    scene_id: str
    policy: str
    instruction: str
    goal: list[float]  # (3,)
    reference_path: list[list[float]]  # (G, 3) ground-truth positions, start first
    actions: list[int]
    poses: list[list[float]]  # (len(actions) + 1, 4) x, y, z, yaw
    stopped: bool
    end_reason: str
    collision_steps: list[int] = field(default_factory=list)
    boxes: list[list[float] | None] = field(default_factory=list)  # (cx, cy, w, h) per step or None
    keyframes: list[list[list[int]] | None] = field(default_factory=list)
    error: str | None = None
    metrics: dict[str, dict] = field(default_factory=dict)  # profile -> per-episode scores (eval/report.py)
    version: int = RECORD_VERSION

    @property
    def key(self) -> tuple[str, str]:
        """(split, episode id): what makes a record unique in a run."""
        return (self.split, self.episode_id)

    @property
    def errored(self) -> bool:
        """The episode ended in an engine error: it is not scored, and a resumed run tries it again."""
        return self.end_reason == "error"

    @property
    def stop_step(self) -> int | None:
        """Index of the STOP action, or None when the episode ended otherwise."""
        return len(self.actions) - 1 if self.stopped else None

    @property
    def collision_step(self) -> int | None:
        """First step whose motion collided, or None."""
        return min(self.collision_steps) if self.collision_steps else None

    def positions(self) -> np.ndarray:
        """(len(poses), 3) visited positions, start first."""
        return np.asarray(self.poses, dtype=np.float64).reshape(-1, 4)[:, :3]

    def to_json(self) -> str:
        """One compact JSON line (no NaN allowed)."""
        return json.dumps(asdict(self), separators=(",", ":"), allow_nan=False)

    @classmethod
    def from_dict(cls, data: dict, file: str | Path = "<memory>", line: int = 0) -> EpisodeRecord:
        """Build a record from a decoded JSON object, checking the fields; raises RecordError."""
        names = set(cls.__dataclass_fields__)
        missing = [
            n
            for n in ("split", "episode_id", "scene_id", "policy", "actions", "poses", "stopped")
            if n not in data
        ]
        if missing:
            raise RecordError(file, line, missing[0], "missing")
        unknown = sorted(set(data) - names)
        if unknown:
            raise RecordError(file, line, unknown[0], f"unknown field (record version {data.get('version')})")
        record = cls(**data)
        _validate(record, file, line)
        return record


def _validate(record: EpisodeRecord, file: str | Path, line: int) -> None:
    if len(record.poses) != len(record.actions) + 1:
        raise RecordError(file, line, "poses", f"{len(record.poses)} poses for {len(record.actions)} actions")
    if any(len(p) != 4 for p in record.poses):
        raise RecordError(file, line, "poses", "every pose must hold 4 numbers (x, y, z, yaw)")
    if len(record.goal) != 3:
        raise RecordError(file, line, "goal", f"expected 3 numbers, got {len(record.goal)}")
    if record.end_reason not in END_REASONS:
        raise RecordError(file, line, "end_reason", f"{record.end_reason!r} is not one of {END_REASONS}")
    if record.stopped and (not record.actions or record.actions[-1] != 0):
        raise RecordError(file, line, "stopped", "stopped episodes must end with the STOP action (0)")
