"""Errors shared across levels: a bad record in an input file, named by file, line and field."""

from __future__ import annotations

import re


class RecordError(ValueError):
    """A malformed record in an input file; the message names the file, the line and the field.

    Args:
        file: path of the file that holds the record.
        line: 1-based line of the record (None when unknown).
        field_name: the offending field, dotted for nested keys (e.g. "traj_map.MapBound").
        problem: what is wrong and, where possible, what was expected.
    """

    def __init__(self, file, line: int | None, field_name: str, problem: str):
        self.file, self.line, self.field_name, self.problem = str(file), line, field_name, problem
        where = f"{self.file}:{line}" if line is not None else self.file
        super().__init__(f"{where}: field '{field_name}': {problem}")


def root_cause(err: BaseException) -> str:
    """The message that says what to change: draccus wraps a config's ValueError in its own parsing errors,
    so those wrappers are unwrapped down to the error they carry. A value draccus cannot decode into the field's
    type names the option: `--steps: expected an int, got 'abc'`. Any other error is kept as it is: its
    message already names the file, record and field (and the cause it wraps would lose them)."""
    decoding = None
    while type(err).__module__.split(".")[0] == "draccus":
        # draccus.utils.DecodingError: the innermost one is the most precise
        if getattr(err, "key_path", None):
            decoding = err
        if err.__cause__ is None:
            break
        err = err.__cause__
    if decoding is not None:
        return f"--{'.'.join(decoding.key_path)}: {_decoding_problem(decoding.message)}"
    return str(err)


def _decoding_problem(message: str) -> str:
    """draccus' decoding message as `expected <type>, got <value>` where it has that shape, else its first
    line."""
    parsed = re.search(r"Couldn't parse (.+) into an? (\w+)", message)
    if parsed:
        kind = parsed.group(2)
        return f"expected {'an' if kind[0] in 'aeiou' else 'a'} {kind}, got {parsed.group(1)}"
    typed = re.search(r"value=(.+?) into field .* of type (.+?)\.\s", message)
    if typed:
        return f"expected a {typed.group(2)}, got {typed.group(1)}"
    return message.strip().splitlines()[0]


def one_line(err: BaseException) -> str:
    """`err` as one line for a command-line error message.

    An error raised in a DataLoader worker reaches the main process as the worker's whole traceback ("Caught
    SchemaError in DataLoader worker process 0. Original Traceback ..."); its last line is the message.
    """
    text = str(err).strip()
    if "Original Traceback" in text:
        last = text.splitlines()[-1]
        text = last.split(": ", 1)[1] if ": " in last else last
    return " ".join(text.split())


def worker_error_name(err: BaseException) -> str | None:
    """The class name of the error a DataLoader worker raised, when `err` is torch's re-raise of it."""
    first = str(err).strip().splitlines()[0] if str(err).strip() else ""
    prefix, _, rest = first.partition("Caught ")
    if prefix or " in DataLoader worker" not in rest:
        return None
    return rest.split(" in DataLoader worker", 1)[0]
