"""Resuming `generate` into a folder: only with the settings the dataset there was generated with.

`meta/toolchain/generate_config.json` records the settings of a dataset (eval also reads its frame size and
city parameters from it). A rerun with other data settings would leave trajectories of both kinds side by
side and overwrite that record, so it is refused, naming the settings that differ, unless `--overwrite=true`
discards the dataset first. Settings that do not change the data (where it goes, how many workers, which
shard, plots, the VLM client's transport) may change between runs. A setting added after the dataset was
recorded counts as recorded at its default (defaults keep the data of earlier versions).
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.toolchain.config import GenerateConfig
from openfly_agent.utils.config import (
    changed_settings,
    config_to_dict,
    describe_changes,
    flat_settings,
    save_config,
)

logger = logging.getLogger(__name__)

# Dotted keys (or prefixes ending in ".") that do not change what is generated.
RUNTIME_KEYS = (
    "output_dir", "workers", "shard", "plots", "overwrite", "instruction_batch",
    "instructions.vlm.concurrency", "instructions.vlm.max_retries", "instructions.vlm.backoff_s",
    "instructions.vlm.timeout_s",
)  # fmt: skip
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
        record: write `cfg` as the dataset's generate_config.json (when none is there, or always on a match).

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
        stored = {**flat_settings(config_to_dict(GenerateConfig())), **flat_settings(stored)}
        changes = describe_changes(changed_settings(stored, config_to_dict(cfg), RUNTIME_KEYS + ignore))
        if changes:
            raise GenerateSettingsError(
                f"{root} holds a dataset generated with other settings ({changes}); run with the same "
                "settings to resume it, pass another --output_dir, or --overwrite=true to discard it"
            )
    if record or not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        save_config(cfg, path)
