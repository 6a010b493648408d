"""Per-episode evaluation records and their JSONL log (appended as episodes finish; the source of truth).

One line per finished episode. A run that is killed leaves at most one partial last line, which
`read_jsonl` drops with a warning (and `EpisodeLog` truncates away before appending). Every table is
recomputed from these records, so a resumed run reports exactly what an uninterrupted one does.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from openfly_agent.utils.errors import RecordError

logger = logging.getLogger(__name__)

END_REASONS = ("stop", "max_steps", "collision", "error", "teleport")
RECORD_VERSION = 1


@dataclass
class EpisodeRecord:
    """What happened in one closed-loop episode.

    `poses[k]` is the pose after `k` actions (`poses[0]` = start), so `len(poses) == len(actions) + 1`;
    STOP leaves the pose unchanged. `collision_steps` are the steps whose motion hit occupied space.
    `boxes[k]` is the landmark box the policy predicted at step k (None: predicted invisible, or a policy
    without boxes); `keyframes[k]` the frame indices of the keyframe sets in its memory after step k.
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


def read_jsonl(path: str | Path, truncate_partial: bool = False) -> list[EpisodeRecord]:
    """Read an episode log. A partial last line (no trailing newline, invalid JSON) is dropped with a warning.

    Args:
        path: the `.jsonl` file; a missing file reads as empty.
        truncate_partial: also cut the partial line off the file, so appends start on a clean line.

    Raises:
        RecordError: a complete line that is not a valid record (names file, line and field).
    """
    path = Path(path)
    if not path.is_file():
        return []
    raw = path.read_bytes()
    records, offset = [], 0
    lines = raw.split(b"\n")
    for number, chunk in enumerate(lines, start=1):
        is_last = number == len(lines)
        if is_last and not chunk:
            break
        try:
            data = json.loads(chunk.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            if is_last:  # written without its newline: the run was killed mid-write
                logger.warning("%s: line %d is incomplete (killed mid-write?); dropping it", path, number)
                if truncate_partial:
                    os.truncate(path, offset)
                break
            raise RecordError(path, number, "<line>", f"not valid JSON ({err})") from err
        if not isinstance(data, dict):
            raise RecordError(path, number, "<line>", "expected a JSON object")
        records.append(EpisodeRecord.from_dict(data, path, number))
        offset += len(chunk) + 1
        if is_last and truncate_partial:  # complete record whose newline was never written
            with open(path, "ab") as handle:
                handle.write(b"\n")
    return records


class EpisodeLog:
    """Append-only writer of one JSONL file; each record is flushed and fsynced when written."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.existing = read_jsonl(self.path, truncate_partial=True)

    def append(self, record: EpisodeRecord) -> None:
        """Append one line and fsync it, so a kill loses at most the line being written."""
        line = record.to_json() + "\n"
        with open(self.path, "a", encoding="utf-8") as handle:
            handle.write(line)
            handle.flush()
            os.fsync(handle.fileno())


def merge_records(groups: list[list[EpisodeRecord]]) -> list[EpisodeRecord]:
    """Union of several logs keyed by (split, episode id), sorted by key. The first finished record of an
    episode wins; a record that ended in an engine error is replaced by any later one (the retry)."""
    merged: dict[tuple[str, str], EpisodeRecord] = {}
    for records in groups:
        for record in records:
            if record.key not in merged or merged[record.key].errored:
                merged[record.key] = record
    return [merged[k] for k in sorted(merged)]


def write_jsonl_atomic(path: str | Path, records: list[EpisodeRecord]) -> None:
    """Write `records` to `path` through a temporary file and a rename (a crash leaves the old file)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", encoding="utf-8") as handle:
        for record in records:
            handle.write(record.to_json() + "\n")
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)
