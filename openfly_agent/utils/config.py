"""Typed config loading: nested dataclasses from YAML plus dotted command-line overrides (draccus).

    cfg = parse_config(TrainConfig, ["--config_path", "configs/train/tiny.yaml", "--optim.lr=1e-4"])

Entry points call this; library code receives the dataclasses.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


def parse_config(
    config_class: type[T], args: list[str] | None = None, config_path: str | Path | None = None
) -> T:
    """Parse `config_class` from an optional YAML file and `--a.b=c` overrides (draccus)."""
    import draccus

    return draccus.parse(config_class=config_class, config_path=config_path, args=args)


def load_yaml_config(config_class: type[T], path: str | Path, overrides: list[str] | None = None) -> T:
    """Load a YAML file into `config_class`, then apply dotted overrides."""
    return parse_config(config_class, args=list(overrides or []), config_path=path)


def config_to_dict(cfg: Any) -> dict:
    """A JSON-friendly dict of a (nested) config dataclass, via draccus' encoder."""
    import draccus

    return json.loads(json.dumps(draccus.encode(cfg)))


def config_from_dict(config_class: type[T], data: dict) -> T:
    """Inverse of `config_to_dict`."""
    import draccus

    return draccus.decode(config_class, data)


def save_config(cfg: Any, path: str | Path) -> None:
    Path(path).write_text(json.dumps(config_to_dict(cfg), indent=2, sort_keys=True) + "\n")


def replace(cfg: T, **changes: Any) -> T:
    return dataclasses.replace(cfg, **changes)
