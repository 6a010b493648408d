"""argparse options generated from a config dataclass (names, types, defaults and help come from the class).

The release commands need plain `--push` / `--repo-id` flags (issue 7), which draccus does not parse reliably,
so each dataclass field becomes one option here instead; nothing is copied by hand.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import typing
from typing import Any, TypeVar

T = TypeVar("T")


def field_docs(cls: type) -> dict[str, str]:
    """Field descriptions from the Google-style `Attributes:` section of a dataclass docstring."""
    docs: dict[str, str] = {}
    current = None
    in_attributes = False
    for line in (cls.__doc__ or "").splitlines():
        stripped = line.strip()
        if stripped == "Attributes:":
            in_attributes = True
            continue
        if not in_attributes or not stripped:
            continue
        match = re.match(r"^(\w+):\s*(.*)$", stripped)
        if match and match[1] in {f.name for f in dataclasses.fields(cls)}:
            current = match[1]
            docs[current] = match[2]
        elif current:
            docs[current] += " " + stripped
    return docs


def add_dataclass_arguments(parser: argparse.ArgumentParser, cls: type, prefix: str = "") -> None:
    """Add one `--field-name` option per field of `cls`; nested dataclass fields become `--<field>.<sub>`."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    for field in dataclasses.fields(cls):
        hint = hints[field.name]
        if dataclasses.is_dataclass(hint):
            add_dataclass_arguments(parser, hint, prefix=f"{prefix}{field.name}.")
            continue
        flag = "--" + (prefix + field.name).replace("_", "-")
        dest = (prefix + field.name).replace(".", "__")
        help_text = _with_default(docs.get(field.name, ""), field).replace("%", "%%")  # argparse formats help
        base, is_list = _base_type(hint)
        if base is bool:
            parser.add_argument(
                flag, dest=dest, action=argparse.BooleanOptionalAction, default=None, help=help_text
            )
            continue
        metavar = field.name.upper()
        nargs = "*" if is_list else None
        parser.add_argument(
            flag, dest=dest, type=base, nargs=nargs, default=None, metavar=metavar, help=help_text
        )


def _with_default(text: str, field: dataclasses.Field) -> str:
    """`text (default: X)` with the dataclass default (argparse's own default stays None: "not given")."""
    if field.default is not dataclasses.MISSING:
        value = field.default
    elif field.default_factory is not dataclasses.MISSING:
        value = field.default_factory()
    else:
        return text
    if value in (None, "", []):  # no default, or one the text describes (e.g. a folder derived from others)
        return text
    if isinstance(value, bool):
        shown = "on" if value else "off"
    elif isinstance(value, list):
        shown = " ".join(map(str, value))
    else:
        shown = str(value)
    return f"{text} (default: {shown})".strip()


def build_dataclass(cls: type[T], namespace: argparse.Namespace, prefix: str = "") -> T:
    """Instantiate `cls` from parsed options; options not given keep the dataclass defaults."""
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    for field in dataclasses.fields(cls):
        hint = hints[field.name]
        if dataclasses.is_dataclass(hint):
            values[field.name] = build_dataclass(hint, namespace, prefix=f"{prefix}{field.name}.")
            continue
        value = getattr(namespace, (prefix + field.name).replace(".", "__"), None)
        if value is not None:
            values[field.name] = value
    return cls(**values)


def _base_type(hint: Any) -> tuple[type, bool]:
    """(element type, is a list) of `str`, `str | None`, `list[str]`, `bool`, `int`, ..."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if typing.get_origin(hint) is list:
        return args[0], True
    if args:  # Optional[X]
        return _base_type(args[0])
    return hint, False
