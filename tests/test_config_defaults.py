"""Every shipped YAML holds only what differs from the defaults: each key is walked against the dataclass default
of its section (of the chosen variant, for a registered choice such as `vision: {type: tiny}`), and a value equal
to it is reported. A section the YAML gives is decoded from its class's field defaults (draccus), which may differ
from the instance its enclosing config defaults to: those are the defaults compared with. A file that merges another (`<<: !include parent.yaml`) may restate a default at the merge's
level when the parent sets that key otherwise (the child's value then undoes the parent's). So may a section file laid
over another config on the command line (`--model=configs/model/reduced-width.yaml`, OVERLAYS) where that config
sets the key otherwise. A recipe stage's `overrides` (train.py settings) are compared with what the recipe's
train_config and model file give that stage: an override equal to it is reported too."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from openfly_agent.data.config import DataConfig
from openfly_agent.eval.config import EvalConfig
from openfly_agent.model.config import ModelConfig
from openfly_agent.recipe.config import RecipeConfig, StageBudget, stage_train_config
from openfly_agent.sim.embedded import EmbeddedSimConfig
from openfly_agent.toolchain.config import GenerateConfig
from openfly_agent.training.config import TrainConfig
from openfly_agent.utils.cli_help import unchecked_defaults
from openfly_agent.utils.config import config_to_dict, flat_settings, load_yaml_config

REPO = Path(__file__).resolve().parents[1]
CONFIG_CLASSES = {  # folder under configs/ -> the dataclass its files parse into
    "train": TrainConfig,
    "model": ModelConfig,
    "data": DataConfig,
    "eval": EvalConfig,
    "toolchain": GenerateConfig,
    "recipe": RecipeConfig,
    "sim": EmbeddedSimConfig,
}
YAML_FILES = sorted(p for folder in CONFIG_CLASSES for p in (REPO / "configs" / folder).rglob("*.yaml"))
OVERLAYS = {"model/reduced-width.yaml": "model/openfly-7b.yaml"}  # section file -> the config it is laid over
INCLUDE = re.compile(r"!include\s+(\S+)")
MERGE = re.compile(r"^(\s*)<<:\s*!include\s+(\S+)\s*$", re.M)


def _own_mapping(path: Path) -> tuple[dict, dict[tuple[str, ...], Path]]:
    """The file's own keys (an included value is the string `!include <path>`, never expanded) and the files it
    merges, by the key path where they merge."""
    text = path.read_text()
    merges: dict[tuple[str, ...], Path] = {}
    lines = text.splitlines()
    for index, line in enumerate(lines):
        match = MERGE.match(line)
        if match:
            indent, parent = len(match[1]), path.parent / match[2]
            prefix = []
            for above in reversed(lines[:index]):  # the enclosing keys: the nearest lines indented less
                stripped = above.lstrip()
                if stripped and not stripped.startswith("#") and len(above) - len(stripped) < indent:
                    prefix.insert(0, stripped.split(":", 1)[0])
                    indent = len(above) - len(stripped)
            merges[tuple(prefix)] = parent
    text = MERGE.sub("", text)
    text = INCLUDE.sub(lambda m: f"'!include {m[1]}'", text)
    return yaml.safe_load(text) or {}, merges


def _effective(path: Path) -> dict:
    """The file with its includes and merges resolved (as the YAML loader reads it)."""
    own, merges = _own_mapping(path)
    own = _resolve_includes(own, path.parent)
    for prefix, parent in merges.items():
        node = own
        for key in prefix:
            node = node[key]
        base = _effective(parent)
        node.update({k: v for k, v in base.items() if k not in node})
    return own


def _resolve_includes(node: Any, folder: Path) -> Any:
    if isinstance(node, str) and node.startswith("!include "):
        return _effective(folder / node.removeprefix("!include "))
    if isinstance(node, dict):
        return {k: _resolve_includes(v, folder) for k, v in node.items()}
    return node


def _same(value: Any, default: Any) -> bool:
    if isinstance(default, tuple):
        default = list(default)
    if isinstance(value, list) and isinstance(default, list):
        return len(value) == len(default) and all(_same(v, d) for v, d in zip(value, default))
    if isinstance(value, bool) or isinstance(default, bool):
        return value is default
    return value == default


def _registry(cls: type) -> type | None:
    """The registered-choice base (draccus `ChoiceRegistry`) of a section class, if it is a variant of one."""
    return next((c for c in cls.__mro__ if "_choice_registry" in vars(c)), None)


def defaults_of(cls: type) -> Any:
    """The defaults a section of `cls` is decoded from: an instance (its `__post_init__` may fill preset sizes),
    or the bare field defaults where those alone are refused (e.g. an eval config without a checkpoint)."""
    try:
        return cls()
    except (ValueError, TypeError):
        return unchecked_defaults(cls)


def _variant_defaults(current: Any, node: dict) -> Any:
    """The default a YAML mapping is compared with: `current`, or the defaults of the variant its `type` names
    when the section is a registered choice."""
    registry = _registry(type(current))
    if registry is not None and "type" in node:
        variant = registry.get_known_choices()[node["type"]]
        if type(current) is not variant:
            return defaults_of(variant)
    return current


def restated_defaults(
    node: dict, default: Any, merges: dict[tuple[str, ...], Path], where: tuple[str, ...] = ()
) -> list[str]:
    """Dotted keys of `node` whose value equals the default. At a level that merges a parent file, a restated
    default that undoes the parent's other value is kept."""
    merged = _effective(merges[where]) if where in merges else {}
    found = []
    names = {f.name for f in dataclasses.fields(default)}
    registry = _registry(type(default))
    for key, value in node.items():
        if key == "type" and registry is not None and value == registry.default_choice_name():
            found.append(".".join((*where, key)))  # the default variant
        if key not in names or isinstance(value, str) and value.startswith("!include "):
            continue
        current = getattr(default, key)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            # a section the YAML gives is decoded from its class's defaults, not from the enclosing default's
            section = defaults_of(type(current))
            found += restated_defaults(value, _variant_defaults(section, value), merges, (*where, key))
        elif _same(value, current) and not (key in merged and not _same(merged[key], current)):
            found.append(".".join((*where, key)))
    return found


def _sets(node: Any, keys: list[str]) -> bool:
    """Whether a nested mapping holds the dotted key `keys`."""
    for key in keys:
        if not isinstance(node, dict) or key not in node:
            return False
        node = node[key]
    return True


@pytest.mark.parametrize("path", YAML_FILES, ids=lambda p: str(p.relative_to(REPO / "configs")))
def test_a_shipped_yaml_restates_no_default(path):
    cls = CONFIG_CLASSES[path.relative_to(REPO / "configs").parts[0]]
    own, merges = _own_mapping(path)
    found = restated_defaults(own, defaults_of(cls), merges)
    base = OVERLAYS.get(path.relative_to(REPO / "configs").as_posix())
    if base is not None:  # a key the config below sets otherwise is what the overlay is for
        under = _effective(REPO / "configs" / base)
        found = [key for key in found if not _sets(under, key.split("."))]
    assert not found, f"{path.relative_to(REPO)} restates defaults: {sorted(set(found))}"


def restated_overrides(cfg: RecipeConfig) -> list[str]:
    """`<stage>.overrides.<key>` of every stage override whose value equals what the recipe's train_config and
    model file already give that stage."""
    stages = {
        "grounding": cfg.grounding,
        "navigation": cfg.navigation,
        "dagger.train": cfg.dagger.train,
        "rl": cfg.rl,
    }
    found = []
    for name, stage in stages.items():
        given = flat_settings(config_to_dict(stage_train_config(cfg, StageBudget(), name)))
        for key, value in flat_settings(stage.overrides).items():
            if key in given and _same(value, given[key]):
                found.append(f"{name}.overrides.{key}")
    return found


RECIPE_FILES = [path for path in YAML_FILES if path.relative_to(REPO / "configs").parts[0] == "recipe"]


@pytest.mark.parametrize("path", RECIPE_FILES, ids=lambda p: str(p.relative_to(REPO / "configs")))
def test_a_recipe_stage_overrides_only_what_its_train_config_sets_otherwise(path):
    found = restated_overrides(load_yaml_config(RecipeConfig, path, []))
    assert not found, f"{path.relative_to(REPO)} restates its train config: {found}"


def test_a_stage_override_equal_to_the_train_config_or_the_model_file_is_reported():
    cfg = RecipeConfig(
        model="configs/model/tiny-adopted.yaml",
        navigation=StageBudget(
            overrides={
                "optim": {"lr": 1.0e-3, "ema_decay": 0.999},
                "model": {"grounding": {"visual_skip": True}},
            }
        ),
        rl=StageBudget(steps=1, overrides={"rl": {"group_size": 4, "kl_coef": 0.1}}),
    )  # configs/train/tiny.yaml's lr is 1.0e-3; tiny-adopted.yaml turns visual_skip on; rl.group_size 4: default
    assert restated_overrides(cfg) == [
        "navigation.overrides.optim.lr",
        "navigation.overrides.model.grounding.visual_skip",
        "rl.overrides.rl.group_size",
    ]
