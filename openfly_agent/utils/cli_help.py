"""Command-line help of the config dataclasses that draccus parses (every entry point's `--help`).

    text = command_help(TrainConfig, argv, prog="train.py", description=..., examples=[...])

draccus builds its `--help` from source comments and gets them wrong when a comment spans lines or sits
inside a wrapped default, and it shows the dataclass defaults rather than the values a YAML preset gives.
Here every flag's text comes from the class source (`ast` + `tokenize`): the comments on the lines of the
field's statement, the comment block right above it, or the `Attributes:` entry of the class docstring; the
default shown is the value in the config the command would run with. A command may leave out of its help the
options that do not apply to the run it describes (`Unlisted`: another stage's section, settings the run
derives); they are still accepted, and one line at the end says how to list them. What a command line may hold
is checked in utils/cli_options.py.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import itertools
import re
import sys
import textwrap
import tokenize
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from openfly_agent.utils.cli_options import (
    CONFIG_FLAG,
    choices_of,
    config_path_of,
    nested_class,
    option_names,
    section_of,
    type_hints,
)
from openfly_agent.utils.config import parse_config

HELP_FLAGS = ("-h", "--help")
WIDTH = 110
FLAG_COLUMN = 36
_NBSP = "\x00"
DIALECT = (  # the one command-line form of every entry point (draccus')
    "Each option takes one value: --<field>=VALUE or --<field> VALUE; a list is written in brackets "
    "(--<field>=[a,b]), a section's field by its dotted name (--<section>.<field>=VALUE), and a yes/no option "
    "alone means true (--<flag> is --<flag>=true)."
)


@dataclass(frozen=True)
class Unlisted:
    """Options a command's `--help` leaves out for the run it describes, and how to list them.

    Attributes:
        names: dotted fields or sections (`data.grounding_root`, `rl`: every field of the section).
        why: what they belong to, e.g. "the RL stage's".
        flags: the options that make them apply, e.g. "--stage=rl": the help line says `<prog> <flags> --help`;
            "" for settings the run derives, which no command line lists.
    """

    names: tuple[str, ...]
    why: str
    flags: str = ""


# -- field descriptions from the source ------------------------------------------------------------------
def _comments_by_line(source: str) -> dict[int, str]:
    comments: dict[int, str] = {}
    try:
        for token in tokenize.generate_tokens(io.StringIO(source).readline):
            if token.type == tokenize.COMMENT:
                text = token.string.lstrip("#").strip()
                if not text.startswith(("fmt:", "noqa", "type:")):
                    comments[token.start[0]] = text
    except (tokenize.TokenError, IndentationError):
        pass
    return comments


def _attribute_docs(cls: type, names: set[str]) -> dict[str, str]:
    """Entries of a Google-style `Attributes:` section (`name: text` or `a, b: text`, continued lines)."""
    docs: dict[str, str] = {}
    current: list[str] = []
    inside = False
    for line in (cls.__doc__ or "").splitlines():
        stripped = line.strip()
        if stripped == "Attributes:":
            inside = True
            continue
        if not inside or not stripped:
            continue
        match = re.match(r"^([\w, ]+):\s*(.*)$", stripped)
        keys = [k.strip() for k in match[1].split(",")] if match else []
        if keys and all(k in names for k in keys):
            current = keys
            for key in keys:
                docs[key] = match[2]
        elif current:
            for key in current:
                docs[key] += " " + stripped
    return docs


@lru_cache(maxsize=256)
def _own_field_docs(cls: type) -> dict[str, str]:
    """Descriptions of the fields `cls` itself declares (see module docstring for where they come from)."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    lines = source.splitlines()
    comments = _comments_by_line(source)
    tree = ast.parse(source)
    class_node = next(node for node in tree.body if isinstance(node, ast.ClassDef))
    docs: dict[str, str] = {}
    statements = [n for n in class_node.body if isinstance(n, (ast.AnnAssign, ast.Assign, ast.Expr))]
    names = {
        n.target.id for n in statements if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name)
    }
    docs.update(_attribute_docs(cls, names))
    for node in statements:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        inline = [comments[n] for n in range(node.lineno, node.end_lineno + 1) if n in comments]
        above: list[str] = []
        line = node.lineno - 1
        while line >= 1 and lines[line - 1].strip().startswith("#") and line in comments:
            above.insert(0, comments[line])
            line -= 1
        text = " ".join(above + inline).strip()
        if text:
            docs[node.target.id] = text
    return docs


def field_docs(cls: type) -> dict[str, str]:
    """{field name: description} of a dataclass, inherited fields included (the subclass' text wins)."""
    docs: dict[str, str] = {}
    for klass in reversed(inspect.getmro(cls)):
        if dataclasses.is_dataclass(klass):
            docs.update(_own_field_docs(klass))
    return docs


def class_summary(cls: type) -> str:
    """First paragraph of the class docstring, on one line."""
    doc = inspect.getdoc(cls) or ""
    return " ".join(doc.split("\n\n")[0].split())


# -- the flag tree ---------------------------------------------------------------------------------------
def _type_name(hint: Any) -> str:
    if isinstance(hint, str):
        return hint.upper()
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (list, tuple, set):
        inner = sorted({_type_name(a) for a in args if a is not Ellipsis})
        return f"[{','.join(inner)}]"
    if args:  # a union such as `int | None`
        names = [_type_name(a) for a in args if a is not type(None)]
        return "|".join(names) + ("?" if type(None) in args else "")
    return getattr(hint, "__name__", str(hint)).upper()


# -- rendering -------------------------------------------------------------------------------------------
def _format_value(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_format_value(v) for v in value) + "]"
    if isinstance(value, str):
        return value if value else '""'
    return str(value)


def _flag_lines(flag: str, text: str) -> list[str]:
    width = WIDTH - FLAG_COLUMN
    body = textwrap.wrap(text, width) or [""]
    if len(flag) + 2 <= FLAG_COLUMN - 1:
        first = f"  {flag}".ljust(FLAG_COLUMN) + body[0]
        return [first] + [" " * FLAG_COLUMN + line for line in body[1:]]
    return [f"  {flag}"] + [" " * FLAG_COLUMN + line for line in body]


def _section_lines(
    cls: type, config: Any, prefix: str, prog: str, skip: frozenset[str] = frozenset()
) -> list[str]:
    """The flags of one config class (its scalar fields), then its nested sections; the dotted fields and
    sections in `skip` are left out."""
    hints, docs = type_hints(cls), field_docs(cls)
    scalar, nested = [], []
    for f in dataclasses.fields(cls):
        if prefix + f.name in skip:
            continue
        value = getattr(config, f.name, None) if config is not None else None
        sub = nested_class(hints.get(f.name))
        if sub is not None:
            if choices_of(sub) and value is not None:  # the chosen variant's fields
                sub = type(value)
            nested.append((f, sub, value))
            continue
        text = docs.get(f.name, "")
        default = f"(default: {_format_value(value)})".replace(" ", _NBSP)  # never split across lines
        flag = f"--{prefix}{f.name} {_type_name(hints.get(f.name, f.type))}"
        scalar += [line.replace(_NBSP, " ") for line in _flag_lines(flag, f"{text} {default}".strip())]
    out = list(scalar)
    for f, sub, value in nested:
        title = f"{prefix}{f.name}"
        summary = field_docs(cls).get(f.name) or class_summary(sub)
        registry = next((c for c in sub.__mro__ if "_choice_registry" in vars(c)), None)
        # a registered choice: its variant in the title, then that variant's own fields
        if registry is not None:
            header = _choice_header(title, registry, value.type, summary, prog)
        else:
            header = f"{title}: {summary}" if summary else f"{title}:"
        out += ["", *_wrap(header, WIDTH)]
        out += _section_lines(sub, value, title + ".", prog, skip)
    return out


def _choice_header(title: str, registry: type, chosen: str, summary: str, prog: str) -> str:
    """The title of a registered choice's section: the chosen variant and its `type` option, the other variants
    and the command that lists one's fields, then the chosen variant's summary."""
    others = [name for name in registry.get_known_choices() if name != chosen]
    header = f"{title}: `{chosen}` ({_whole(f'--{title}.type={chosen}')}"
    if others:
        which = f"other variants: {', '.join(others)}" if others[1:] else f"the other variant: {others[0]}"
        header += f"; {which}, whose fields {_whole(f'{prog} --{title}.type={others[0]} --help')} lists"
    rest = summary.removeprefix(f"`{chosen}`:").strip()
    return f"{header})" + (f": {rest}" if rest else "")


def _whole(text: str) -> str:
    """`text` kept on one line by `_wrap` (an option or a command: a line never starts with a bare `--x`)."""
    return text.replace(" ", _NBSP)


def _wrap(text: str, width: int, indent: str = "") -> list[str]:
    """`text` wrapped at `width`, never inside a `_whole` part or at a hyphen."""
    lines = textwrap.wrap(text, width, subsequent_indent=indent, break_on_hyphens=False)
    return [line.replace(_NBSP, " ") for line in lines]


def unchecked_defaults(cls: type) -> Any:
    """An instance of `cls` holding its field defaults, built without `__post_init__` (whose checks may
    refuse the bare defaults, e.g. a policy that needs a checkpoint)."""
    config = object.__new__(cls)
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            value = f.default
        elif f.default_factory is not dataclasses.MISSING:
            value = f.default_factory()
        else:
            value = None
        object.__setattr__(config, f.name, value)
    return config


def config_help(
    cls: type,
    config: Any,
    prog: str,
    description: str,
    examples: Sequence[str],
    config_note: str | None = None,
    extra_options: Sequence[tuple[str, str]] = (),
    unlisted: Sequence[Unlisted] = (),
) -> str:
    """The `--help` text of a command that parses `cls`.

    Args:
        cls: the config dataclass.
        config: the config the command would run with (its values are the defaults shown); None shows the
            dataclass defaults.
        prog: the command, e.g. "train.py".
        description: what the command does (one paragraph).
        examples: command lines shown at the end.
        config_note: where the shown defaults come from (e.g. "configs/train/tiny.yaml").
        extra_options: (flag, text) of options the command takes besides the fields.
        unlisted: options left out, each group named on one line of its own at the end (`Unlisted`).
    """
    if config is None:
        config = unchecked_defaults(cls)
    skip = frozenset(name for group in unlisted for name in group.names)
    lines = [f"usage: {prog} [--config_path YAML] [--<field>=VALUE ...]", ""]
    lines += textwrap.wrap(" ".join(description.split()), WIDTH)
    lines += ["", *textwrap.wrap(DIALECT, WIDTH)]
    if config_note:
        lines += ["", *textwrap.wrap(config_note, WIDTH)]
    lines += ["", "options:"]
    lines += _flag_lines("-h, --help", "show this help and exit")
    lines += _flag_lines(f"--{CONFIG_FLAG} YAML", "a YAML file whose values replace the defaults below")
    for flag, text in extra_options:
        lines += _flag_lines(flag, text)
    lines += ["", *_section_lines(cls, config, "", prog, skip)]
    if unlisted:
        lines += ["", *_unlisted_lines(cls, config, prog, unlisted)]
    lines += ["", "examples:", *(f"  {example}" for example in examples)]
    return "\n".join(lines) + "\n"


def _unlisted_lines(cls: type, config: Any, prog: str, unlisted: Sequence[Unlisted]) -> list[str]:
    """One line per group of options the help leaves out: their names, how many, and how to list them."""
    every = [line.split()[0][2:] for line in _section_lines(cls, config, "", prog) if line.startswith("  --")]
    lines = ["not listed for this run (accepted all the same):"]
    for group in unlisted:
        counts = {
            name: sum(1 for flag in every if flag == name or flag.startswith(f"{name}."))
            for name in group.names
        }
        present = [name for name, count in counts.items() if count]  # a field of another variant counts none
        if not present:
            continue
        count = sum(counts.values())
        names = ", ".join(f"{name}.*" if section_of(cls, name) else name for name in present)
        text = f"{names} ({count} option{'s' if count != 1 else ''}): {group.why}"
        if group.flags:
            text += "; " + _whole(f"{prog} {group.flags} --help")
        lines += [f"  {line}" for line in _wrap(text, WIDTH - 2, indent="    ")]
    return lines


def command_help(
    cls: type,
    args: Sequence[str],
    prog: str,
    description: str,
    examples: Sequence[str],
    extra_options: Sequence[tuple[str, str]] = (),
    placeholders: dict[str, str] | None = None,
    unlisted: Callable[[Any], Sequence[Unlisted]] | None = None,
) -> str:
    """The `--help` of a command line `args` (help flags included) that parses `cls`: every option with the
    value the same command line without `--help` would run with.

    A command line that does not parse (yet) shows the values of its `--config_path` YAML, else the dataclass
    defaults. `placeholders` are values of required fields, dotted names too ({"checkpoint": "x"}), used only
    to get past their check where the command line does not give them: the fewest that do are filled (so a
    value the YAML gives stays), and those fields are shown unset.
    `unlisted(config)` names the options that do not apply to the config shown (`Unlisted`).
    """
    args = without_help(args)
    config_path = config_path_of(args)
    given = set(option_names(args))
    flags = {name: f"--{name}={value}" for name, value in (placeholders or {}).items() if name not in given}
    missing = list(flags)
    fills = [names for size in range(len(missing) + 1) for names in itertools.combinations(missing, size)]
    attempts = [([*args, *(flags[name] for name in names)], names) for names in fills]
    if config_path:
        attempts.append((["--config_path", config_path, *flags.values()], missing))
    config = None
    for attempt, filled in attempts:
        try:
            config = parse_config(cls, attempt)
        except Exception:  # a bad option, or a required field missing: the next attempt
            continue
        for name in filled:
            *sections, field_name = name.split(".")
            owner = config
            for section in sections:
                owner = getattr(owner, section)
            object.__setattr__(owner, field_name, None)
        break
    note = (
        f"Defaults below are the values of {config_path} (and of the options given)." if config_path else None
    )
    left_out = unlisted(config if config is not None else unchecked_defaults(cls)) if unlisted else ()
    return config_help(cls, config, prog, description, examples, note, extra_options, left_out)


def commands_usage(
    prog: str,
    summary: str,
    commands: dict[str, str],
    examples: Sequence[str],
    name_width: int = 10,
    options: str = "[--<field>=VALUE ...]",
) -> str:
    """The `--help` of a command-line with sub-commands: usage line, `summary`, one line per command (name ->
    what it does), the examples."""
    lines = [f"usage: {prog} {{{','.join(commands)}}} {options}   (<command> --help for its options)", ""]
    lines += [
        summary,
        "",
        "commands:",
        *(f"  {name:<{name_width}} {text}" for name, text in commands.items()),
    ]
    lines += ["", "examples:", *(f"  {example}" for example in examples)]
    return "\n".join(lines) + "\n"


def choose_command(
    argv: Sequence[str], commands: Sequence[str], prog: str, usage: str
) -> tuple[str, list[str]] | int:
    """The first argument of a command-line with sub-commands, and the rest; or the exit code when there is none to
    run: 0 after printing `usage` for `--help`, 2 after one line on stderr for a missing or unknown command."""
    if argv and argv[0] in ("-h", "--help"):
        print(usage, end="")  # noqa: T201 (the command-line help of an entry point)
        return 0
    if not argv or argv[0] not in commands:
        what = f"unknown command {argv[0]!r}" if argv else "no command given"
        print(f"{prog}: {what}; choose one of {', '.join(commands)} (--help lists them)", file=sys.stderr)  # noqa: T201
        return 2
    return argv[0], list(argv[1:])


def wants_help(args: Sequence[str]) -> bool:
    """Whether the command line asks for help."""
    return any(arg in HELP_FLAGS for arg in args)


def without_help(args: Sequence[str]) -> list[str]:
    """The command line minus `-h` / `--help`."""
    return [arg for arg in args if arg not in HELP_FLAGS]
