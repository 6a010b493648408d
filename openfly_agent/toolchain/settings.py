"""Resuming `generate` into a folder: only with the settings the dataset there was generated with.

`meta/toolchain/generate_config.json` records the settings of a dataset; `meta/generation_settings.json`, written
with it, the few that its readers need (frame size and city parameters, data/generation_settings.py). A rerun with other data settings would leave trajectories of both kinds side by
side and overwrite that record, so it is refused, naming the settings that differ, unless `--overwrite=true`
discards the dataset first. Settings that do not change the data (where it goes, how many workers, which
shard, plots, the VLM client's transport) may change between runs. A setting added after the dataset was
recorded counts as recorded at its default (defaults keep the data of earlier versions), except the `val`
split's settings (`ADDED_KEYS`), which an older dataset takes as given: the rerun adds the `val` split and
leaves the other splits as they are.
"""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
from collections.abc import Iterator
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.data.generation_settings import GenerationSettings
from openfly_agent.toolchain.config import GenerateConfig
from openfly_agent.utils.config import (
    changed_settings,
    config_to_dict,
    describe_changes,
    flat_settings,
    save_config,
)
from openfly_agent.utils.files import first_missing_dir, remove_created_dirs, remove_empty_tree

logger = logging.getLogger(__name__)

# Dotted keys (or prefixes ending in ".") that do not change what is generated.
RUNTIME_KEYS = (
    "output_dir", "workers", "shard", "plots", "overwrite", "instruction_batch",
    "instructions.vlm.concurrency", "instructions.vlm.max_retries", "instructions.vlm.backoff_s",
    "instructions.vlm.timeout_s",
)  # fmt: skip
# Settings added after datasets were generated: a dataset whose record lacks them resumes with them, which
# generates only what they add (the `val` split's units); the record is then rewritten with them.
ADDED_KEYS = ("scenes.val_seen_per_scene", "scenes.val_seeds", "scenes.val_unseen_per_scene")
DATASET_PARTS = (C.DATASET_ANNOTATION_DIR, C.DATASET_TRAJ_DIR, "meta")  # what generate writes under the root


class GenerateSettingsError(ValueError):
    """The output folder holds a dataset generated with other settings; the message lists them."""


def discard_dataset(root: Path) -> None:
    """Delete what `generate` wrote under `root` (annotations, trajectories, meta); other files stay."""
    for name in DATASET_PARTS:
        path = root / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


def prepare_output(cfg: GenerateConfig, ignore: tuple[str, ...] = (), record: bool = True) -> None:
    """Make `cfg.output_dir` ready: discard it with `overwrite`, refuse other settings, record these.

    Args:
        cfg: the generate config.
        ignore: more keys (or "prefix.") allowed to differ, e.g. "dagger." for the policy DAgger command,
            which adds episodes to a dataset generated with its own DAgger settings.
        record: write `cfg` as the dataset's generate_config.json and its generation settings (when no
            config is there, or always on a match).

    Raises:
        GenerateSettingsError: the folder holds a dataset of other settings and `overwrite` is false.
    """
    root = Path(cfg.output_dir)
    path = root / C.TOOLCHAIN_CONFIG_JSON
    if cfg.overwrite and any((root / name).exists() for name in DATASET_PARTS):
        logger.warning("overwrite=true: discarding the dataset in %s", root)
        discard_dataset(root)
    elif path.is_file():
        try:
            stored = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise GenerateSettingsError(
                f"{path} is not readable ({err}): pass --overwrite=true to generate anew"
            ) from err
        absent = tuple(key for key in ADDED_KEYS if key not in flat_settings(stored))
        stored = {**flat_settings(config_to_dict(GenerateConfig())), **flat_settings(stored)}
        changes = describe_changes(
            changed_settings(stored, config_to_dict(cfg), RUNTIME_KEYS + absent + ignore)
        )
        if changes:
            raise GenerateSettingsError(
                f"{root} holds a dataset generated with other settings ({changes}); run with the same "
                "settings to resume it, pass another --output_dir, or --overwrite=true to discard it"
            )
    if record or not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        save_config(cfg, path)
        generation_settings(cfg).save(root)


def generation_settings(cfg: GenerateConfig) -> GenerationSettings:
    """What the readers of the dataset `cfg` generates need of its settings."""
    return GenerationSettings(
        width=cfg.render.width,
        height=cfg.render.height,
        city_size_m=cfg.scenes.city_size_m,
        city_buildings=cfg.scenes.city_buildings,
    )


@contextlib.contextmanager
def record_kept_on_success(root: Path) -> Iterator[None]:
    """Around a first `generate` into `root` (no settings record there yet): when it fails before it has written
    anything but the records (the config and the generation settings), they go again, with the empty folders the
    run made, so the corrected command is not refused as "a dataset generated with other settings". A run that
    wrote episodes keeps its records (the same command resumes it); files that were there before are never
    touched."""
    record = root / C.TOOLCHAIN_CONFIG_JSON
    records = {record, root / C.GENERATION_SETTINGS_JSON}
    first_run, created = not record.exists(), first_missing_dir(root)
    before = _files_under(root) if first_run else set()
    try:
        yield
    except BaseException:
        if first_run and record.exists() and _files_under(root) - before <= records:
            for path in records - before:
                path.unlink(missing_ok=True)
            for name in DATASET_PARTS:
                remove_empty_tree(root / name)
            remove_created_dirs(root, created)
        raise


def _files_under(root: Path) -> set[Path]:
    return {path for path in root.rglob("*") if not path.is_dir()} if root.is_dir() else set()
