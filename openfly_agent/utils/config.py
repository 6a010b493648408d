"""Typed config loading: nested dataclasses from YAML plus dotted command-line overrides (draccus).

    cfg = parse_config(TrainConfig, ["--config_path", "configs/train/tiny.yaml", "--optim.lr=1e-4"])

Entry points call this; library code receives the dataclasses.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Any, TypeVar

from openfly_agent.utils.cli_options import (
    CommandLineError,
    bare_flags_as_true,
    check_options,
    config_path_of,
    nested_class,
    type_hints,
    unknown_choice,
)
from openfly_agent.utils.errors import root_cause

T = TypeVar("T")


def parse_config(
    config_class: type[T], args: list[str] | None = None, config_path: str | Path | None = None
) -> T:
    """Parse `config_class` from an optional YAML file and `--a.b=c` overrides (draccus); a yes/no option
    given alone (`--push`) means `--push=true`; a section given a YAML file (`--model=<file>.yaml`) takes that
    file's keys over its own (`section_files_first`).

    Raises:
        CommandLineError: an option that names no field (`UnknownOptionError`, with the closest field: "did you
            mean"), a registered choice that names no variant, a list without brackets, a `--config_path` that
            is missing, a config file that is not YAML; one line each.
        FileNotFoundError: a `config_path` argument that is missing.
        draccus.utils.ParsingError: a value that does not parse or that the config refuses.
    """
    import argparse
    import sys

    import draccus
    import yaml

    args = list(sys.argv[1:] if args is None else args)
    check_options(config_class, args)
    args = bare_flags_as_true(config_class, args)
    args = [_resolved_config_arg(arg, args[i - 1] if i else None) for i, arg in enumerate(args)]
    args = section_files_first(config_class, args)
    if config_path is not None:
        config_path = resolve_config_path(config_path)
    typed = config_path_of(args)  # the YAML the command line names
    if typed is not None and not Path(typed).is_file():
        raise CommandLineError(f"--config_path {typed}: no such file")
    yaml_file = f"--config_path {typed}" if typed is not None else str(config_path)
    try:  # exit_on_error=False: an argparse error is raised here, not printed with draccus' usage dump
        return draccus.parse(
            config_class=config_class, config_path=config_path, args=args, exit_on_error=False
        )
    except argparse.ArgumentError as err:
        raise CommandLineError(str(err)) from err
    except draccus.utils.ParsingError as err:
        if isinstance(err.__cause__, yaml.YAMLError):
            problem = " ".join(str(err.__cause__).split())
            raise CommandLineError(f"{yaml_file}: not valid YAML ({problem})") from err
        choice = _choice_in_file(config_class, err)
        if choice:
            raise CommandLineError(choice) from err
        raise


CHOICE_MISSING = re.compile(r"Couldn't find a choice class for '(.*)' in")  # draccus' decoding message


def _choice_in_file(config_class: type, err: BaseException) -> str | None:
    """The one line of a registered choice that a YAML file sets to no variant (`sim: {type: habitat}`), naming
    the variants; None for any other error."""
    while err is not None:
        found = CHOICE_MISSING.search(str(getattr(err, "message", "")))
        if found and getattr(err, "key_path", None):
            return unknown_choice(config_class, ".".join(err.key_path), found.group(1))
        err = err.__cause__
    return None


REPO_ROOT = Path(__file__).resolve().parents[2]  # a source checkout: configs/ sits next to the package


def resolve_config_path(path: str | Path) -> Path:
    """Where a file that ships with the repository is: `path` as given (relative to the working directory),
    else, for a relative path that is not there, the same path inside the repository, so `configs/...` and
    `data_cards/...` work from any folder.

    Outputs and datasets are never resolved this way: they stay relative to the working directory.
    """
    path = Path(path)
    if path.is_absolute() or path.exists():
        return path
    in_repo = REPO_ROOT / path
    return in_repo if in_repo.is_file() else path


def with_config_path(args: list[str], default: str | Path) -> list[str]:
    """`args` with `--config_path <default>` in front when they name no config file (a command's default
    preset: the plain command runs exactly what that YAML says)."""
    if any(arg == "--config_path" or arg.startswith("--config_path=") for arg in args):
        return list(args)
    return ["--config_path", str(default), *args]


def _resolved_config_arg(arg: str, previous: str | None) -> str:
    if arg.startswith("--config_path="):
        return "--config_path=" + str(resolve_config_path(arg.split("=", 1)[1]))
    if previous == "--config_path" and not arg.startswith("--"):
        return str(resolve_config_path(arg))
    return arg


SECTION_FILE_SUFFIXES = (".yaml", ".yml", ".json")


def section_files_first(config_class: type, args: list[str]) -> list[str]:
    """`args` with each section given a file (`--model=configs/model/reduced-width.yaml` or `--model <file>`) as
    draccus' `--model=include <file>`, which lays the file's keys over that section of the config file (a
    partial section: the keys it does not name keep their values), moved in front of the other options so
    that a dotted option (`--model.memory.grid=2`) still wins over the file, wherever it stands."""
    files, rest, index = [], [], 0
    while index < len(args):
        arg = args[index]
        name, has_value, value = arg[2:].partition("=") if arg.startswith("--") else ("", "", "")
        if (
            arg.startswith("--")
            and not has_value
            and index + 1 < len(args)
            and not args[index + 1].startswith("--")
        ):
            value, index = args[index + 1], index + 1
        if name and value.endswith(SECTION_FILE_SUFFIXES) and _section_of(config_class, name) is not None:
            files.append(f"--{name}=include {resolve_config_path(value)}")
        else:
            rest += [arg, value] if value and not has_value else [arg]
        index += 1
    return files + rest


def _section_of(config_class: type, name: str) -> type | None:
    """The dataclass of the section a dotted option names (`model.vision`), else None (a plain field)."""
    section: type | None = config_class
    for part in name.split("."):
        section = nested_class(type_hints(section).get(part)) if section is not None else None
    return section


def load_yaml_config(config_class: type[T], path: str | Path, overrides: list[str] | None = None) -> T:
    """Load a YAML file into `config_class`, then apply dotted overrides."""
    return parse_config(config_class, args=list(overrides or []), config_path=path)


def config_to_dict(cfg: Any) -> dict:
    """A JSON-friendly dict of a (nested) config dataclass, via draccus' encoder: the one serialiser of every
    config (train_config.json, the model sections of a checkpoint's config.json, a dataset's settings)."""
    import draccus

    return json.loads(json.dumps(draccus.encode(cfg)))


def config_from_dict(config_class: type[T], data: dict) -> T:
    """Inverse of `config_to_dict`: missing keys take their defaults.

    Raises:
        ValueError: one line naming the class and the field (an unknown key, a value of the wrong type, or a
            value the config refuses).
    """
    import draccus
    from draccus.utils import DraccusException

    try:
        return draccus.decode(config_class, data)
    except DraccusException as err:
        raise ValueError(f"{config_class.__name__}: {root_cause(err).removeprefix('--')}") from err


def flat_settings(node: Any, prefix: str = "") -> dict[str, Any]:
    """A nested config dict (as `config_to_dict` writes it) as `{"a.b.c": value}`."""
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for key, value in node.items():
            out.update(flat_settings(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: node}


def is_listed(key: str, listed: tuple[str, ...]) -> bool:
    """Whether the dotted `key` is in `listed`: an exact key, or under a section given as a prefix ending in "."."""
    return any(key == k or (k.endswith(".") and key.startswith(k)) for k in listed)


def changed_settings(
    stored: dict, current: dict, allowed: tuple[str, ...] = ()
) -> dict[str, tuple[Any, Any]]:
    """`{dotted key: (stored value, current value)}` for every setting that differs between two config dicts.

    How a command that resumes into a folder refuses other settings (`toolchain generate`, `train.py --resume`).

    Args:
        stored: the config dict recorded in the folder.
        current: the config dict of this run.
        allowed: keys that may differ (left out): exact dotted keys, or prefixes ending in "." (a section).
    """
    old, new = flat_settings(stored), flat_settings(current)
    keys = sorted(k for k in set(old) | set(new) if not is_listed(k, allowed))
    return {k: (old.get(k), new.get(k)) for k in keys if old.get(k) != new.get(k)}


def describe_changes(changes: dict[str, tuple[Any, Any]], limit: int = 8) -> str:
    """`a.b: 1 -> 2; c: 'x' -> 'y'` (the first `limit`, then how many more), for a one-line message."""
    shown = [f"{key}: {old!r} -> {new!r}" for key, (old, new) in list(changes.items())[:limit]]
    more = len(changes) - limit
    return "; ".join(shown) + (f"; and {more} more" if more > 0 else "")


def save_config(cfg: Any, path: str | Path) -> None:
    Path(path).write_text(json.dumps(config_to_dict(cfg), indent=2, sort_keys=True) + "\n")


def replace(cfg: T, **changes: Any) -> T:
    return dataclasses.replace(cfg, **changes)
