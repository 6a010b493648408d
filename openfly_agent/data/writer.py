"""Write generated episodes in the OpenFly release layout: per-trajectory parquet + annotation JSON.

Layout of a dataset root (the release's, so one reader serves both):
    traj/<scene>/astar_data/<category>/<folder>.parquet   one per trajectory, one row per kept frame
    Annotation/parts/<split>/<scene>[.part-<k>].json      records, rewritten as trajectories finish
                                                          (at most PART_MAX_RECORDS per file)
    Annotation/{train,seen,unseen,val}.json               merged from the parts by finalize()
    meta/info.json, meta/stats.json, meta/data_files.json counts and scenes; action statistics; file lists
Parts make generation resumable (`has_episode`) and shardable (writers on several machines write
different scenes; copy the folders together and call `finalize()`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.frames import encode_image
from openfly_agent.data.labels import check_action_sequence
from openfly_agent.data.parquet_io import TRAJECTORY_SCHEMA, trajectory_table, write_table_atomic
from openfly_agent.data.records import episode_from_record, parse_episode_id, record_from_episode
from openfly_agent.data.schema import Episode, SchemaError
from openfly_agent.data.stats import action_histogram, compute_action_statistics
from openfly_agent.utils.files import write_text_atomic
from openfly_agent.utils.progress import progress_bar

logger = logging.getLogger(__name__)

IMAGE_FORMATS = {"png": "png", "jpeg": "jpg", "jpg": "jpg"}
DATA_FILES_JSON = "meta/data_files.json"
PART_MAX_RECORDS = 256  # records per part file: a write rewrites at most this many (not the whole scene)


def write_json_atomic(path: Path, data) -> None:
    """Write JSON through a temporary file and a rename, so a crash never leaves half a file."""
    write_text_atomic(path, json.dumps(data, ensure_ascii=False) + "\n")


def _read_records(path: Path) -> list[dict]:
    try:
        records = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise SchemaError(str(path), "<file>", "<json>", f"not valid JSON: {err}") from err
    if not isinstance(records, list):
        raise SchemaError(str(path), "<file>", "<json>", "expected a list of records")
    return records


class OpenFlyDatasetWriter:
    """Writes episodes and their frames under `root`; one writer per scene at a time.

    Args:
        root: dataset root (created if needed).
        image_format: "png" (lossless, as released) or "jpeg" (quality 95).
        part_max_records: records per annotation part file before a new one is started.
    """

    def __init__(self, root: str | Path, image_format: str = "png", part_max_records: int = PART_MAX_RECORDS):
        if part_max_records < 1:
            raise ValueError(f"part_max_records={part_max_records}: must be >= 1")
        if image_format not in IMAGE_FORMATS:
            raise ValueError(f"image_format={image_format!r}: choose one of {sorted(IMAGE_FORMATS)}")
        self.root = Path(root)
        self.image_format = image_format
        self._ext = IMAGE_FORMATS[image_format]
        self.part_max_records = part_max_records
        self._part_of: dict[str, Path] | None = None  # episode id -> part file, loaded on first use
        # part file -> {episode id: record as JSON text}; a part is rewritten without re-encoding old records
        self._part_text: dict[Path, dict[str, str]] = {}

    # --- paths ---------------------------------------------------------------------------------------
    def trajectory_path(self, episode_id: str) -> Path:
        """`<root>/traj/<episode_id>.parquet`."""
        parse_episode_id(episode_id, str(self.root), episode_id)
        return self.root / C.DATASET_TRAJ_DIR / f"{episode_id}.parquet"

    def part_path(self, split: str, scene_id: str) -> Path:
        """The part file a new record of (split, scene) goes to.

        `<root>/Annotation/parts/<split>/<scene_id>.json`, then `<scene_id>.part-<k>.json` (k = 1, 2, ...) once
        the previous one holds `part_max_records` records, so each write rewrites a bounded file.
        """
        folder = self.root / C.DATASET_PARTS_DIR / split
        path, k = folder / f"{scene_id}.json", 0
        while len(self._records_text(path)) >= self.part_max_records:
            k += 1
            path = folder / f"{scene_id}.part-{k}.json"
        return path

    def _part_for(self, episode: Episode) -> Path:
        """The episode's existing part file when it stays in its split (replaced in place), else a new slot."""
        existing = self._part_index().get(episode.episode_id)
        if existing is not None and existing.parent.name == episode.split:
            return existing
        return self.part_path(episode.split, episode.scene_id)

    def _part_index(self) -> dict[str, Path]:
        if self._part_of is None:
            self._part_of = {}
            for part in sorted((self.root / C.DATASET_PARTS_DIR).glob("*/*.json")):
                for record in _read_records(part):
                    self._part_of[record.get("image_path")] = part
        return self._part_of

    # --- writing -------------------------------------------------------------------------------------
    def has_episode(self, episode_id: str) -> bool:
        """True when the episode's parquet and its annotation record both exist (it can be skipped)."""
        return episode_id in self._part_index() and self.trajectory_path(episode_id).is_file()

    def write_episode(self, episode: Episode, frames: Sequence[np.ndarray]) -> Path:
        """Write one trajectory: its parquet (atomic), then its record in the scene's part file (atomic).

        Args:
            episode: the episode; `split` must be one of constants.SPLITS, `episode_id` must be
                `<scene_id>/astar_data/<category>/<folder>`, visible boxes valid (cx, cy, w, h).
            frames: (H, W, 3) uint8 RGB, one per kept frame.

        Returns:
            The parquet path. Writing an episode again replaces its parquet and record.

        Raises:
            SchemaError: the episode breaks the schema (nothing is written then).
        """
        self._check_episode(episode, frames)
        encoded = [encode_image(f, self._ext) for f in frames]
        table = trajectory_table(episode, encoded, self._ext)
        path = self.trajectory_path(episode.episode_id)
        write_table_atomic(table, path)
        self._put_record(record_from_episode(episode), self._part_for(episode))
        return path

    def _check_episode(self, episode: Episode, frames: Sequence[np.ndarray]) -> None:
        eid = episode.episode_id
        scene_id, _ = parse_episode_id(eid, eid, eid)
        if scene_id != episode.scene_id:
            raise SchemaError(
                eid, eid, "scene_id", f"{episode.scene_id!r} is not the first part of the episode id"
            )
        if episode.split not in C.SPLITS:
            raise SchemaError(eid, eid, "split", f"{episode.split!r}: choose one of {C.SPLITS}")
        check_action_sequence(episode.actions, eid, eid)
        if len(frames) != len(episode):
            raise SchemaError(eid, eid, "frames", f"{len(frames)} frames for {len(episode)} kept frames")
        for t, frame in enumerate(frames):
            frame = np.asarray(frame)
            if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
                raise SchemaError(
                    eid, t, "frames", f"expected (H, W, 3) uint8 RGB, got {frame.dtype} {frame.shape}"
                )
        shapes = {np.asarray(f).shape for f in frames}
        if len(shapes) != 1:
            raise SchemaError(eid, eid, "frames", f"frames differ in shape: {sorted(shapes)}")

    def _records_text(self, part: Path) -> dict[str, str]:
        if part not in self._part_text:
            records = _read_records(part) if part.is_file() else []
            self._part_text[part] = {r.get("image_path"): json.dumps(r, ensure_ascii=False) for r in records}
        return self._part_text[part]

    def _write_part(self, part: Path) -> None:
        write_text_atomic(part, "[" + ",\n".join(self._records_text(part).values()) + "]\n")

    def _put_record(self, record: dict, part: Path) -> None:
        """Add (or replace) `record` in `part`, rewriting the file atomically (tmp + rename)."""
        index = self._part_index()
        episode_id = record["image_path"]
        old_part = index.get(episode_id)
        if old_part is not None and old_part != part:  # the episode moved split: drop the old record
            self._records_text(old_part).pop(episode_id, None)
            self._write_part(old_part)
        texts = self._records_text(part)
        texts.pop(episode_id, None)
        texts[episode_id] = json.dumps(record, ensure_ascii=False)
        self._write_part(part)
        index[episode_id] = part

    # --- finalize ------------------------------------------------------------------------------------
    def finalize(self, strict: bool = True) -> dict:
        """Merge the parts into `Annotation/{train,seen,unseen,val}.json` and write `meta/`.

        Args:
            strict: raise when a record has no parquet file (True), or leave it out with a warning.

        Returns:
            The content of `meta/info.json`.

        Raises:
            SchemaError: a bad record, or the same episode in two part files.
            FileNotFoundError: (strict) records whose parquet file is missing.
        """
        by_split: dict[str, list[Episode]] = {}
        data_files: dict[str, list[str]] = {}
        for split in C.SPLITS:
            records, episodes = self._merged_records(split, strict)
            write_json_atomic(self.root / C.DATASET_ANNOTATION_DIR / C.ANNOTATION_FILES[split], records)
            by_split[split] = episodes
            data_files[split] = [f"{C.DATASET_TRAJ_DIR}/{e.episode_id}.parquet" for e in episodes]
        info = self._info(by_split)
        stats_episodes = by_split[C.SPLIT_TRAIN] or [e for eps in by_split.values() for e in eps]
        has_model_steps = any(np.any(e.actions >= 0) for e in stats_episodes)
        stats = compute_action_statistics(stats_episodes) if has_model_steps else {}
        write_json_atomic(self.root / C.DATASET_STATS_JSON, stats)
        write_json_atomic(self.root / DATA_FILES_JSON, data_files)
        write_json_atomic(self.root / C.DATASET_INFO_JSON, info)
        logger.info(
            "finalized %s: %d episodes, %d frames", self.root, info["num_episodes"], info["num_frames"]
        )
        return info

    def _merged_records(self, split: str, strict: bool) -> tuple[list[dict], list[Episode]]:
        """Records of `split` from its part files and their episodes, sorted by id; duplicates raise."""
        owner: dict[str, Path] = {}
        merged, missing = [], []
        parts = sorted((self.root / C.DATASET_PARTS_DIR / split).glob("*.json"))
        for part in progress_bar(parts, desc=f"finalize {split}", leave=False, disable=len(parts) < 50):
            for i, record in enumerate(_read_records(part)):
                episode_id = record.get("image_path") if isinstance(record, dict) else None
                if not isinstance(episode_id, str):
                    raise SchemaError(str(part), i, "image_path", f"missing or not a string: {episode_id!r}")
                if episode_id in owner:
                    raise SchemaError(
                        str(part), i, "image_path", f"{episode_id!r} is also in {owner[episode_id]}"
                    )
                owner[episode_id] = part
                if not self.trajectory_path(episode_id).is_file():
                    missing.append(episode_id)
                    continue
                merged.append((episode_id, record, episode_from_record(record, str(part), i, split)))
        if missing:
            message = f"{len(missing)} record(s) of split {split} have no parquet file, e.g. {missing[:5]}"
            if strict:
                raise FileNotFoundError(message)
            logger.warning("%s; left out of the annotation files", message)
        merged.sort(key=lambda item: item[0])
        return [record for _, record, _ in merged], [episode for _, _, episode in merged]

    def _info(self, by_split: dict[str, list[Episode]]) -> dict:
        everything = [e for eps in by_split.values() for e in eps]
        return {
            "schema_version": C.DATASET_SCHEMA_VERSION,
            "image_format": self.image_format,
            "num_episodes": len(everything),
            "num_frames": int(sum(len(e) for e in everything)),
            "scenes": sorted({e.scene_id for e in everything}),
            "splits": {
                split: {
                    "episodes": len(eps),
                    "frames": int(sum(len(e) for e in eps)),
                    "scenes": sorted({e.scene_id for e in eps}),
                    "annotation_file": f"{C.DATASET_ANNOTATION_DIR}/{C.ANNOTATION_FILES[split]}",
                }
                for split, eps in by_split.items()
            },
            "episodes_with_boxes": sum(e.has_boxes for e in everything),
            "action_counts": {str(a): n for a, n in action_histogram(everything).items()},
            "stats_split": C.SPLIT_TRAIN if by_split[C.SPLIT_TRAIN] else "all",
            "features": {f.name: str(f.type) for f in TRAJECTORY_SCHEMA},
            "layout": {
                "trajectories": f"{C.DATASET_TRAJ_DIR}/<scene>/astar_data/<category>/<folder>.parquet",
                "annotations": f"{C.DATASET_ANNOTATION_DIR}/{{train,seen,unseen,val}}.json",
                "parts": f"{C.DATASET_PARTS_DIR}/<split>/<scene>.json",
                "data_files": DATA_FILES_JSON,
            },
        }
