"""Checks that run before any compute, each failing with a `PreflightError` that says what to change.

Covered: an unwritable or already-used output folder, a batch size that does not divide, a missing or
malformed dataset, and a checkpoint whose tensors do not match the configured architecture.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import uuid
from collections.abc import Mapping
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.data.config import DataConfig
from openfly_agent.data.openfly_reader import (
    annotation_path,
    load_openfly_dataset,
    non_strict_hint,
    part_files,
)
from openfly_agent.data.schema import SchemaError
from openfly_agent.model.persistence.checkpoint_path import (
    UnreadableWeightsError,
    checkpoint_files,
    open_safetensors,
)
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.config import BatchConfig, BatchSizeError

logger = logging.getLogger(__name__)


class PreflightError(RuntimeError):
    """A run cannot start; the message names the file / field at fault and what to change."""


def check_output_dir(output_dir: str | Path, resume: bool) -> Path | None:
    """Create `output_dir`, prove it is writable, and match it with `resume`.

    Returns:
        The checkpoint to resume from (None for a fresh run).

    Raises:
        PreflightError: the folder cannot be created or written, it already holds checkpoints of another run
            and `resume` is false, or `resume` is true and it holds none.
    """
    folder = Path(output_dir)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".write-test-{uuid.uuid4().hex}"
        probe.write_text("ok")
        probe.unlink()
    except OSError as err:
        raise PreflightError(
            f"output_dir {folder} is not writable ({err.strerror}): choose another --output_dir"
        ) from err
    latest = CheckpointManager(folder, keep_last=1).latest()
    if latest is not None and not resume:
        raise PreflightError(
            f"output_dir {folder} already holds checkpoints (newest {latest.name}): pass --resume=true to "
            "continue that run, or choose a new --output_dir"
        )
    if resume and latest is None:
        raise PreflightError(f"--resume=true but {folder / 'checkpoints'} holds no complete checkpoint")
    return latest


def check_batch(batch: BatchConfig, world_size: int) -> int:
    """Gradient-accumulation steps for `world_size` processes; `PreflightError` if it does not divide."""
    try:
        return batch.accumulation_steps(world_size)
    except BatchSizeError as err:
        raise PreflightError(str(err)) from err


def resolve_val_split(data: DataConfig) -> tuple[DataConfig, str | None]:
    """`data` with the split validation reads: the default `val`, or `test_seen` on a dataset without a `val`
    split (the released OpenFly data, a dataset generated before the split existed), and then the warning to log.

    The warning (None when the split is used as set) is logged once the run's checks passed, so a run that fails
    one still says one line. A missing root is left to `check_dataset_root`, which names it.
    """
    root = Path(data.root)
    if data.val_split != C.SPLIT_VAL or not root.is_dir() or _has_records(root, C.SPLIT_VAL):
        return data, None
    warning = (
        f"dataset {root} has no {C.SPLIT_VAL} split (released data, or generated before it existed): validating "
        f"on {C.SPLIT_TEST_SEEN}, so choices made on it are made on a test split (rerunning generate with a "
        "shipped toolchain config adds the val split, docs/TOOLCHAIN.md)"
    )
    return dataclasses.replace(data, val_split=C.SPLIT_TEST_SEEN), warning


def _has_records(root: Path, split: str) -> bool:
    """Whether `split` of the dataset at `root` holds a record (its annotation file, else its part files)."""
    path = annotation_path(root, split)
    if path.is_file():
        try:
            return bool(json.loads(path.read_text()))
        except (OSError, json.JSONDecodeError):
            return True  # unreadable: reading the split names the fault
    return bool(part_files(root, split))


def check_dataset_root(data: DataConfig) -> None:
    """The dataset root exists and has an annotation for every configured split (files only, no parsing)."""
    root = Path(data.root)
    if not root.is_dir():
        raise PreflightError(
            f"dataset root {root} does not exist: generate it (python -m openfly_agent.toolchain generate "
            f"--output_dir={root}), or download the released OpenFly data as {C.RELEASED_DATA_CARD} says and "
            "pass its folder as --data.root"
        )
    for split in dict.fromkeys((C.SPLIT_TRAIN, data.val_split, data.test_split)):
        if not annotation_path(root, split).is_file() and not part_files(root, split):
            raise PreflightError(
                f"dataset {root} has no annotation for split {split!r}: "
                f"expected {annotation_path(root, split)}"
            )


def load_split(data: DataConfig, split: str) -> list:
    """Episodes of `split`; schema errors become a `PreflightError` naming file, record and field."""
    try:
        episodes = load_openfly_dataset(data.root, split, options=data.reader)
    except (SchemaError, FileNotFoundError, json.JSONDecodeError) as err:
        strict = isinstance(err, SchemaError) and data.reader.strict
        hint = non_strict_hint(err, "--data.reader.strict") if strict else ""
        raise PreflightError(f"dataset {data.root}, split {split!r}: {err}{hint}") from err
    if not episodes:
        raise PreflightError(f"dataset {data.root}, split {split!r} has no episodes")
    return episodes


def check_frames_readable(frame_store, episodes: list) -> None:
    """Decode the first frame of the first episode, so a missing `traj/` folder fails now, not mid-epoch."""
    episode = episodes[0]
    try:
        frame_store.frame(episode, 0)
    except Exception as err:  # any reader error: missing parquet, corrupt PNG, ...
        raise PreflightError(f"cannot read frames of episode {episode.episode_id}: {err}") from err


def checkpoint_tensor_shapes(folder: str | Path) -> dict[str, tuple[int, ...]]:
    """Tensor names and shapes of a checkpoint's safetensors files, read from the headers only."""
    try:
        files = checkpoint_files(Path(folder))
    except FileNotFoundError as err:
        raise PreflightError(str(err)) from None
    shapes: dict[str, tuple[int, ...]] = {}
    try:
        for path in files:
            with open_safetensors(path) as f:
                for key in f.keys():  # noqa: SIM118 (safe_open is not a dict)
                    shapes[key] = tuple(f.get_slice(key).get_shape())
    except UnreadableWeightsError as err:
        raise PreflightError(str(err)) from None
    return shapes


def compare_shapes(
    expected: Mapping[str, tuple[int, ...]], found: Mapping[str, tuple[int, ...]], source: str
) -> None:
    """Raise a `PreflightError` listing missing, unexpected and mis-shaped tensors (first few of each)."""
    missing = sorted(set(expected) - set(found))
    unexpected = sorted(set(found) - set(expected))
    wrong = sorted(k for k in set(expected) & set(found) if tuple(expected[k]) != tuple(found[k]))
    if not (missing or unexpected or wrong):
        return
    lines = [f"{source} does not match the configured model architecture:"]
    if wrong:
        lines.append(
            "  shape differs: " + ", ".join(f"{k} {found[k]} vs {tuple(expected[k])}" for k in wrong[:5])
        )
    if missing:
        lines.append(f"  missing ({len(missing)}): {missing[:5]}")
    if unexpected:
        lines.append(f"  unexpected ({len(unexpected)}): {unexpected[:5]}")
    lines.append(
        "  use the model config the checkpoint was trained with (its config.json), or another checkpoint"
    )
    raise PreflightError("\n".join(lines))


def diff_configs(expected: Mapping, found: Mapping, prefix: str = "model") -> list[str]:
    """Dotted paths where two nested config dicts differ, as `path: found -> expected` lines."""
    lines = []
    for key in sorted(set(expected) | set(found)):
        a, b = expected.get(key), found.get(key)
        path = f"{prefix}.{key}"
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            lines += diff_configs(a, b, path)
        elif a != b:
            lines.append(f"{path}: checkpoint {b!r}, config {a!r}")
    return lines
