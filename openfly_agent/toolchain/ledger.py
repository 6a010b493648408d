"""Per-scene record of finished work units (`meta/toolchain/units/<scene>.jsonl`) for resume and summary.

The parent process appends one JSON line per unit (episode written, or rejected with a reason). Files are
per scene, so shards written on different machines merge by copying folders together. A torn last line
(crash while appending) is skipped with a warning; that unit is simply generated again.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from openfly_agent import constants as C

logger = logging.getLogger(__name__)

STATUS_OK, STATUS_REJECTED = "ok", "rejected"


class UnitLedger:
    """Append-only JSON lines per scene under `<root>/meta/toolchain/units/`."""

    def __init__(self, root: str | Path):
        self.dir = Path(root) / C.TOOLCHAIN_UNITS_DIR

    def path(self, scene_id: str) -> Path:
        return self.dir / f"{scene_id}.jsonl"

    def read(self, scene_id: str) -> list[dict]:
        """All records of one scene (torn or invalid lines are skipped and logged)."""
        path = self.path(scene_id)
        if not path.is_file():
            return []
        records = []
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
            if not line.strip():
                continue
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                logger.warning("%s: line %d is not valid JSON (interrupted write?); ignored", path, number)
        return records

    def read_all(self) -> list[dict]:
        """Records of every scene present (e.g. after merging shards)."""
        return [r for path in sorted(self.dir.glob("*.jsonl")) for r in self.read(path.stem)]

    def append(self, scene_id: str, record: dict) -> None:
        """Append one record; a torn last line (no newline) is closed first so the new record stays whole."""
        path = self.path(scene_id)
        path.parent.mkdir(parents=True, exist_ok=True)
        line = (json.dumps(record, sort_keys=True) + "\n").encode("utf-8")
        with path.open("ab+") as handle:
            if handle.seek(0, 2) > 0:
                handle.seek(-1, 2)
                if handle.read(1) != b"\n":
                    line = b"\n" + line
            handle.write(line)
            handle.flush()
