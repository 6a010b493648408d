"""Dataset release: a generated dataset root -> a Hub dataset folder (parquet, annotations, card)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import yaml

from openfly_agent.constants import (
    ANNOTATION_FILES,
    DATASET_ANNOTATION_DIR,
    DATASET_INFO_JSON,
    DATASET_STATS_JSON,
    DATASET_TRAJ_DIR,
    MODEL_CARD_NAME,
)
from openfly_agent.data.writer import DATA_FILES_JSON
from openfly_agent.hub.config import DatasetReleaseConfig
from openfly_agent.hub.folder_utils import DEFAULT_RELEASE_ROOT, link_or_copy, prepare_output_dir, read_json
from openfly_agent.hub.model_card import split_front_matter
from openfly_agent.utils.config import resolve_config_path

logger = logging.getLogger(__name__)

TRAJECTORY_CONFIG = "trajectories"
# count of frames -> the Hub's size_categories label
_SIZE_CATEGORIES = ((1_000, "n<1K"), (10_000, "1K<n<10K"), (100_000, "10K<n<100K"), (1_000_000, "100K<n<1M"))


def build_dataset_release(cfg: DatasetReleaseConfig) -> Path:
    """Write the dataset release folder and return it.

    Copies (hard-links when possible) `traj/**.parquet`, `Annotation/{train,seen,unseen,val}.json` (those with
    trajectories) and `meta/`, and writes `README.md` from `cfg.card` with YAML `configs` so
    `datasets.load_dataset(<repo>)` gives the frames of one split per annotation file. The annotation JSON files
    travel as they are, for the OpenFly reader (`datasets` infers one file format per repository, so they get no
    config of their own).

    Raises:
        FileNotFoundError: the root, its annotations or meta, a trajectory parquet or the card is missing.
    """
    root = Path(cfg.dataset_root)
    splits = _split_trajectories(root)
    out = prepare_output_dir(
        cfg.output_dir or DEFAULT_RELEASE_ROOT / cfg.repo_id.split("/")[1], cfg.overwrite
    )
    for files in splits.values():
        for rel in files:
            link_or_copy(root / rel, out / rel)
    for split, name in ANNOTATION_FILES.items():
        if split in splits:
            link_or_copy(root / DATASET_ANNOTATION_DIR / name, out / DATASET_ANNOTATION_DIR / name)
    for rel in (DATASET_INFO_JSON, DATASET_STATS_JSON, DATA_FILES_JSON):
        if (root / rel).is_file():
            link_or_copy(root / rel, out / rel)
    card = render_dataset_card(  # a shipped card (data_cards/...) is found from any working directory
        resolve_config_path(cfg.card), splits, num_frames=_count_frames(root, splits), repo_id=cfg.repo_id
    )
    (out / MODEL_CARD_NAME).write_text(card)
    logger.info("dataset release folder %s: %d trajectories", out, sum(len(f) for f in splits.values()))
    return out


def _split_trajectories(root: Path) -> dict[str, list[str]]:
    """Map each split that holds trajectories to its parquet paths (relative to root) via its annotation file (id =
    path in traj/)."""
    if not root.is_dir():
        raise FileNotFoundError(f"dataset root {root} does not exist")
    splits: dict[str, list[str]] = {}
    for split, name in ANNOTATION_FILES.items():
        path = root / DATASET_ANNOTATION_DIR / name
        if not path.is_file():
            continue
        records = read_json(path)
        files = []
        for index, record in enumerate(records):
            episode_id = record.get("image_path") if isinstance(record, dict) else None
            if not isinstance(episode_id, str):
                raise ValueError(f"{path}: record {index}: field 'image_path' is missing or not a string")
            rel = f"{DATASET_TRAJ_DIR}/{episode_id}.parquet"
            if not (root / rel).is_file():
                raise FileNotFoundError(
                    f"{path}: record {index}: trajectory file {root / rel} does not exist"
                )
            files.append(rel)
        if files:  # a split without trajectories (an empty val.json) is left out: the Hub's loader refuses it
            splits[split] = sorted(set(files))
    if not splits:
        raise FileNotFoundError(
            f"{root / DATASET_ANNOTATION_DIR}: no annotation file with trajectories "
            f"({', '.join(ANNOTATION_FILES.values())})"
        )
    if not (root / DATASET_INFO_JSON).is_file():
        raise FileNotFoundError(
            f"{root / DATASET_INFO_JSON} is missing: finalize the dataset before releasing it"
        )
    return splits


def _count_frames(root: Path, splits: dict[str, list[str]]) -> int:
    import pyarrow.parquet as pq

    return sum(pq.ParquetFile(root / rel).metadata.num_rows for files in splits.values() for rel in files)


def dataset_configs(splits: dict[str, list[str]]) -> list[dict[str, Any]]:
    """The card's `configs`: one parquet config; each split lists the trajectory files of its annotations."""
    order = [split for split in ANNOTATION_FILES if split in splits]
    data_files = [{"split": split, "path": splits[split]} for split in order]
    return [{"config_name": TRAJECTORY_CONFIG, "data_files": data_files, "default": True}]


def render_dataset_card(card_path: Path, splits: dict[str, list[str]], num_frames: int, repo_id: str) -> str:
    """The card template with `configs` and `size_categories` filled in (YAML re-dumped: it always parses)."""
    if not card_path.is_file():
        raise FileNotFoundError(f"dataset card template {card_path} does not exist (see data_cards/)")
    meta, body = split_front_matter(card_path.read_text())
    meta["configs"] = dataset_configs(splits)
    meta["size_categories"] = [
        next((label for limit, label in _SIZE_CATEGORIES if num_frames < limit), "1M<n<10M")
    ]
    text = f"---\n{yaml.safe_dump(meta, sort_keys=False, allow_unicode=True, width=1000)}---\n{body}"
    text = text.replace("{{repo_id}}", repo_id).replace("{{ repo_id }}", repo_id)
    _validate_dataset_card(text)
    return text


def _validate_dataset_card(text: str) -> None:
    from huggingface_hub import DatasetCard

    DatasetCard(text, ignore_metadata_errors=False)
