"""What a command line of a config dataclass may hold, checked before draccus parses it (one dialect for every
entry point: draccus' dotted options).

    check_options(TrainConfig, ["--optim.lrr=1"])   # UnknownOptionError: ... did you mean --optim.lr?

Each option takes one value (`--a.b=c` or `--a.b c`), a list is written in brackets (`--split=[a,b]`), a section
takes only a YAML file, a registered choice (`--sim.type`) one of its variants, and a yes/no option alone means
true (`bare_flags_as_true`). A command line that breaks these rules is one `CommandLineError` line naming the
option, never draccus' usage dump.
"""

from __future__ import annotations

import dataclasses
import difflib
import typing
from collections.abc import Iterable, Sequence
from typing import Any

CONFIG_FLAG = "config_path"


class CommandLineError(ValueError):
    """A command line that cannot run as written (an option, a value or a file it names); the message is the one
    line an entry point prints before it exits with code 2."""


class UnknownOptionError(CommandLineError):
    """A command-line option that names no config field; the message suggests the closest one."""


def type_hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except Exception:  # an annotation that cannot be resolved: fall back to the raw strings
        return {f.name: f.type for f in dataclasses.fields(cls)}


def nested_class(hint: Any) -> type | None:
    """The dataclass of a field typed `SomeConfig` or `SomeConfig | None`, else None."""
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return hint
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if len(args) == 1 and isinstance(args[0], type) and dataclasses.is_dataclass(args[0]):
        return args[0]
    return None


def known_options(cls: type, prefix: str = "") -> dict[str, bool]:
    """{dotted option: takes any sub-key} for every field of `cls` and its nested sections.

    A section (`optim`) is an option too: draccus reads `--optim=<yaml file>`. Fields typed `dict` accept any
    sub-key. A registered-choice section has `type` and the fields of every variant (draccus refuses those of
    another variant than the chosen one).
    """
    options: dict[str, bool] = {}
    hints = type_hints(cls)
    for f in dataclasses.fields(cls):
        name = prefix + f.name
        nested = nested_class(hints.get(f.name))
        origin = typing.get_origin(hints.get(f.name))
        options[name] = origin is dict or hints.get(f.name) is dict
        if nested is not None:
            variants = choices_of(nested)
            if variants:
                options[name + ".type"] = False
            for section in variants.values() or [nested]:
                options.update(known_options(section, prefix=name + "."))
    return options


def choices_of(cls: type) -> dict[str, type]:
    """The registered variants of a section typed by a draccus choice registry (`vision: {type: tiny}`), else {}."""
    known = getattr(cls, "get_known_choices", None)
    return dict(known()) if known is not None else {}


def _option_hint(cls: type, name: str) -> Any:
    """The type of the field a dotted option names (None for a name that is no field)."""
    owner: Any = cls
    *sections, last = name.split(".")
    for part in sections:
        owner = nested_class(type_hints(owner).get(part)) if owner is not None else None
    return type_hints(owner).get(last) if owner is not None else None


def _is_list(hint: Any) -> bool:
    """Whether a field typed `hint` holds a list (`list[str]`, `list[int] | None`)."""
    return any(typing.get_origin(h) in (list, tuple) for h in (hint, *typing.get_args(hint)))


def section_of(cls: type, name: str) -> type | None:
    """The section class a dotted option names (`sim` -> SimSettings, the registry of eval's simulators), else
    None."""
    section: Any = cls
    for part in name.split("."):
        section = nested_class(type_hints(section).get(part)) if section is not None else None
    return section


def _is_flag(cls: type, name: str) -> bool:
    hint = _option_hint(cls, name)
    return hint is bool or (typing.get_args(hint) and set(typing.get_args(hint)) <= {bool, type(None)})


def _without_value(args: Sequence[str], index: int) -> bool:
    """Whether the option at `index` is written without a value (`--push`, then nothing or another option)."""
    return "=" not in args[index] and (index + 1 == len(args) or args[index + 1].startswith("--"))


def bare_flags_as_true(cls: type, args: Sequence[str]) -> list[str]:
    """`args` with a yes/no option given alone (`--push`, `--resume`) written as draccus reads it
    (`--push=true`)."""
    return [
        f"{arg}=true" if arg.startswith("--") and _without_value(args, i) and _is_flag(cls, arg[2:]) else arg
        for i, arg in enumerate(args)
    ]


def option_names(args: Sequence[str]) -> list[str]:
    """The option names of a command line (`--a.b=1`, `--a.b 1` -> "a.b"); values are skipped."""
    return [arg[2:].split("=", 1)[0] for arg in args if arg.startswith("--") and len(arg) > 2]


def option_values(args: Sequence[str]) -> list[tuple[str, str | None]]:
    """(name, value) of each option of a command line (`--a.b=1` and `--a.b 1` -> ("a.b", "1")); the value is
    None for an option written alone."""
    out = []
    for index, arg in enumerate(args):
        if not arg.startswith("--") or len(arg) <= 2:
            continue
        name, has_value, value = arg[2:].partition("=")
        if not has_value:
            following = args[index + 1] if index + 1 < len(args) else None
            value = following if following is not None and not following.startswith("--") else None
        out.append((name, value))
    return out


def check_options(cls: type, args: Sequence[str], extra: Iterable[str] = (CONFIG_FLAG,)) -> None:
    """Raise `UnknownOptionError` for the first option that names no field (with the closest one), or for a
    second value after an option (each option takes one value: a list is written `--split=[a,b]`);
    `CommandLineError` for a registered choice that names no variant or a list written without brackets.

    Args:
        cls: the config dataclass the command line is parsed into.
        args: the command line (draccus form: `--a.b=c` or `--a.b c`).
        extra: option names the command accepts besides the fields.
    """
    options = known_options(cls)
    known = set(options) | set(extra)
    open_prefixes = [name + "." for name, any_key in options.items() if any_key]
    for index, arg in enumerate(args):
        if arg.startswith("--") or (
            index and args[index - 1].startswith("--") and "=" not in args[index - 1]
        ):
            continue
        owner = next((a for a in reversed(args[:index]) if a.startswith("--")), None)
        if owner is None:
            raise UnknownOptionError(f"unexpected value {arg!r}: every value follows its --option")
        name = owner[2:].split("=", 1)[0]
        raise UnknownOptionError(
            f"--{name} takes one value, {arg!r} is a second one: write a list as --{name}=[a,b] "
            "(--help lists every option)"
        )
    for index, name in enumerate(option_names(args)):
        if name in known or any(name.startswith(p) for p in open_prefixes):
            _check_section_value(cls, name, [a for a in args if a.startswith("--")][index], args)
            continue
        close = difflib.get_close_matches(name, sorted(known), n=1, cutoff=0.6)
        if not close:  # a typo in the last part of a dotted name: compare with the siblings only
            parent = name.rsplit(".", 1)[0] + "." if "." in name else ""
            siblings = [k for k in known if k.startswith(parent) and "." not in k[len(parent) :]]
            close = difflib.get_close_matches(name, siblings, n=1, cutoff=0.5)
        hint = f"; did you mean --{close[0]}?" if close else ""
        raise UnknownOptionError(f"unknown option --{name}{hint} (--help lists every option)")
    for index, arg in enumerate(args):
        name = arg[2:]
        if arg.startswith("--") and _without_value(args, index) and not _is_flag(cls, name) and name in known:
            raise UnknownOptionError(f"--{name} needs a value: --{name}=VALUE (--help lists every option)")
    for name, value in option_values(args):
        if value is not None:
            _check_value(cls, name, value)


NULL_VALUES = ("null", "None", "~")  # YAML's none, which an optional list takes as is


def unknown_choice(cls: type, section_name: str, value: str) -> str | None:
    """The one-line message for a registered-choice section of `cls` (`sim`) set to `value`, a variant it does not
    have; None when `value` is one of its variants or the section is no registered choice."""
    section = section_of(cls, section_name)
    variants = choices_of(section) if section is not None else {}
    if not variants or value in variants:
        return None
    return (
        f"--{section_name}.type: unknown choice {value!r}; choose one of {', '.join(variants)} "
        "(--help lists every option)"
    )


def _check_value(cls: type, name: str, value: str) -> None:
    """A registered choice names one of its variants; a list is written in brackets (`--split=[a]`)."""
    section_name, _, last = name.rpartition(".")
    problem = unknown_choice(cls, section_name, value) if last == "type" and section_name else None
    if problem:
        raise CommandLineError(problem)
    if _is_list(_option_hint(cls, name)) and not value.startswith("[") and value not in NULL_VALUES:
        raise CommandLineError(f"--{name} takes a list, written in brackets: --{name}=[{value}]")


def _check_section_value(cls: type, name: str, option: str, args: Sequence[str]) -> None:
    """A section (`--sim`) takes a YAML file only: `--sim embedded` names the field to set instead."""
    section = section_of(cls, name)
    if section is None:
        return
    value = option.split("=", 1)[1] if "=" in option else None
    if value is None and option in args and args.index(option) + 1 < len(args):
        value = args[args.index(option) + 1]
    if value is not None and not value.startswith("--") and not value.endswith((".yaml", ".yml", ".json")):
        # a registered choice names its variant first
        first = "type" if choices_of(section) else dataclasses.fields(section)[0].name
        raise UnknownOptionError(
            f"--{name} is a section: set its fields (--{name}.{first}={value}) or give it a YAML file "
            "(--help lists every option)"
        )


def config_path_of(args: Sequence[str]) -> str | None:
    """The value of `--config_path X` / `--config_path=X` in a command line, or None."""
    for index, arg in enumerate(args):
        if arg == f"--{CONFIG_FLAG}" and index + 1 < len(args):
            return args[index + 1]
        if arg.startswith(f"--{CONFIG_FLAG}="):
            return arg.split("=", 1)[1]
    return None
