"""Read OpenFly-format annotation files (released `train/seen/unseen.json` or our parts) into episodes.

Each record is validated field by field; reader options then fix how the -1 / -2 phases and merged
forward labels are treated. Strict mode raises on the first bad record; otherwise bad records are
logged, skipped and collected in a `ReadReport`.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.labels import (
    apply_takeoff_landing,
    check_action_sequence,
    move_merged_forward_to_start,
)
from openfly_agent.data.records import episode_from_record, four_number_positions
from openfly_agent.data.schema import Episode, SchemaError
from openfly_agent.utils.progress import progress_bar

logger = logging.getLogger(__name__)

WHOLE_FILE = "<file>"  # the record of a SchemaError about the whole annotation file
SPLIT_OF_FILE = {name: split for split, name in C.ANNOTATION_FILES.items()}  # "seen.json" -> "test_seen"


@dataclass
class ReadReport:
    """What a read saw and changed: records, episodes kept, one `SchemaError` per skipped record (non-strict),
    the take-off / landing frames trimmed or labels mapped (`takeoff_landing`), the `pos` entries cut from 4
    numbers to 3, and how many forward labels `merged_forward_position="start"` changed or left unresolved."""

    records: int = 0
    episodes: int = 0
    errors: list[SchemaError] = field(default_factory=list)
    takeoff_landing_trimmed: int = 0
    takeoff_landing_mapped: int = 0
    positions_cut: int = 0
    forward_relabelled: int = 0
    forward_unresolved: int = 0

    def add(self, error: SchemaError) -> None:
        self.errors.append(error)
        logger.warning("skipping a bad record: %s", error)

    def changes(self) -> dict[str, int]:
        """{what the reader did: how often}, every kind of repair (zeros included)."""
        return {
            "malformed records skipped": len(self.errors),
            "take-off/landing frames trimmed": self.takeoff_landing_trimmed,
            "take-off/landing labels mapped to ascend/descend": self.takeoff_landing_mapped,
            "four-number positions cut to three": self.positions_cut,
            "forward labels moved to where their motion starts": self.forward_relabelled,
            "forward labels left as released (not a pure move)": self.forward_unresolved,
        }


def describe_changes(before: dict[str, int], after: dict[str, int]) -> str:
    """`164 take-off/landing frames trimmed, 22 four-number positions cut to three` (what changed between two
    `ReadReport.changes()`), or `nothing`."""
    done = [f"{after[kind] - before[kind]} {kind}" for kind in after if after[kind] != before[kind]]
    return ", ".join(done) or "nothing"


def non_strict_hint(error: SchemaError, flag: str) -> str:
    """What a command adds to a strict read's error about one record: its option (`flag`) that skips such
    records instead; "" for an error about the whole file (not JSON, not a list)."""
    if error.record == WHOLE_FILE:
        return ""
    return f" (a strict read stops at the first malformed record: {flag}=false skips each one, logged and counted)"


def _load_json_list(path: Path) -> list:
    try:
        with path.open("r", encoding="utf-8") as f:
            data = json.load(f)
    except json.JSONDecodeError as err:
        raise SchemaError(str(path), WHOLE_FILE, "<json>", f"not valid JSON: {err}") from err
    if not isinstance(data, list):
        raise SchemaError(
            str(path), WHOLE_FILE, "<json>", f"expected a list of records, got {type(data).__name__}"
        )
    return data


def read_annotation_file(
    path: str | Path,
    options: ReaderOptions | None = None,
    split: str | None = None,
    report: ReadReport | None = None,
) -> list[Episode]:
    """Episodes of one annotation JSON file (a list of records), reader options applied.

    Args:
        path: `train.json` / `seen.json` / `unseen.json` of the release, one of our part files, or any
            file in that format (e.g. the official `eval_test.json`).
        options: label handling and strictness (defaults: ReaderOptions()).
        split: split for records without a `split` field; by default inferred from the release file name
            (train.json -> train, seen.json -> test_seen, unseen.json -> test_unseen), else None.
        report: filled with counts and the skipped records' errors (non-strict mode).

    Raises:
        SchemaError: in strict mode, for the first record that breaks the schema (file, record, field).
    """
    path = Path(path)
    options = options or ReaderOptions()
    report = report if report is not None else ReadReport()
    split = split if split is not None else SPLIT_OF_FILE.get(path.name)
    episodes, seen_ids = [], {}
    records = _load_json_list(path)
    before = report.changes()
    for index, record in enumerate(
        progress_bar(records, desc=path.name, leave=False, disable=len(records) < 10_000)
    ):
        report.records += 1
        try:
            episode = episode_from_record(record, str(path), index, split)
            if episode.episode_id in seen_ids:
                raise SchemaError(
                    str(path), index, "image_path", f"duplicate of record {seen_ids[episode.episode_id]}"
                )
            check_action_sequence(episode.actions, str(path), index)
            phases = int((episode.actions < 0).sum())  # -1 take-off and -2 landing labels
            episode = apply_takeoff_landing(episode, options.takeoff_landing)
            if options.merged_forward_position == "start":
                episode, changed, unresolved = move_merged_forward_to_start(episode)
                report.forward_relabelled += changed
                report.forward_unresolved += unresolved
        except SchemaError as err:
            if options.strict:
                raise
            report.add(err)
            continue
        report.positions_cut += four_number_positions(record)
        if options.takeoff_landing == "trim":
            report.takeoff_landing_trimmed += phases
        elif options.takeoff_landing == "map":
            report.takeoff_landing_mapped += phases
        seen_ids[episode.episode_id] = index
        episodes.append(episode)
    report.episodes += len(episodes)
    logger.info(
        "%s: %d of %d records read; the reader changed %s",
        path, len(episodes), len(records), describe_changes(before, report.changes()),
    )  # fmt: skip
    if report.errors:
        logger.warning(
            "%s: kept %d of %d records (%d bad)", path, len(episodes), report.records, len(report.errors)
        )
    return episodes


def annotation_path(root: str | Path, split: str) -> Path:
    """`<root>/Annotation/<train|seen|unseen>.json` of `split`."""
    if split not in C.ANNOTATION_FILES:
        raise ValueError(f"unknown split {split!r}: choose one of {C.SPLITS}")
    return Path(root) / C.DATASET_ANNOTATION_DIR / C.ANNOTATION_FILES[split]


def part_files(root: str | Path, split: str) -> list[Path]:
    """Our per-scene part files of `split`, sorted: `<root>/Annotation/parts/<split>/<scene>.json`."""
    return sorted((Path(root) / C.DATASET_PARTS_DIR / split).glob("*.json"))


def load_openfly_dataset(
    root: str | Path, split: str, options: ReaderOptions | None = None, report: ReadReport | None = None
) -> list[Episode]:
    """Episodes of one split of a dataset root (released OpenFly or generated by our writer).

    Reads `<root>/Annotation/<file>.json`; when that file does not exist yet but part files do (a
    generation still running, or `finalize()` not called), reads the parts and says so.

    Args:
        root: dataset root holding `Annotation/` (and `traj/` for the frames, see FrameStore).
        split: one of constants.SPLITS.
        options: reader options (defaults: ReaderOptions()).
        report: filled in non-strict mode.
    """
    path = annotation_path(root, split)
    if path.is_file():
        return read_annotation_file(path, options, split=split, report=report)
    parts = part_files(root, split)
    if not parts:
        raise FileNotFoundError(
            f"{path} does not exist and {Path(root) / C.DATASET_PARTS_DIR / split} has no parts"
        )
    logger.warning(
        "%s missing: reading %d part files (call OpenFlyDatasetWriter.finalize())", path, len(parts)
    )
    episodes: list[Episode] = []
    for part in parts:
        episodes += read_annotation_file(part, options, split=split, report=report)
    return episodes


def split_episodes(
    episodes: Sequence[Episode], holdout_fraction: float, seed: int = 0
) -> tuple[list[Episode], list[Episode]]:
    """Deterministic (train, held-out) split by a hash of each episode id (stable as the set grows).

    Args:
        episodes: the episodes to split.
        holdout_fraction: share of episodes held out, in [0, 1).
        seed: changes which episodes are held out.
    """
    if not 0.0 <= holdout_fraction < 1.0:
        raise ValueError(f"holdout_fraction={holdout_fraction}: must be in [0, 1)")
    keep, held = [], []
    for episode in episodes:
        digest = hashlib.sha256(f"{seed}:{episode.episode_id}".encode()).digest()
        u = int.from_bytes(digest[:8], "big") / 2**64  # uniform in [0, 1)
        (held if u < holdout_fraction else keep).append(episode)
    return keep, held
