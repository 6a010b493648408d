"""The JSONL log of evaluation records (`rollout.record.EpisodeRecord`), appended as episodes finish; the source of truth.

One line per finished episode. A run that is killed leaves at most one partial last line, which
`read_jsonl` drops with a warning (and `EpisodeLog` truncates away before appending). Every table is
recomputed from these records, so a resumed run reports exactly what an uninterrupted one does.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.utils.errors import RecordError
from openfly_agent.utils.files import write_atomic

logger = logging.getLogger(__name__)


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

    def dump(tmp: Path) -> None:
        with open(tmp, "w", encoding="utf-8") as handle:
            for record in records:
                handle.write(record.to_json() + "\n")
            handle.flush()
            os.fsync(handle.fileno())

    write_atomic(path, dump)
