"""Errors shared across levels: a bad record in an input file, named by file, line and field."""

from __future__ import annotations


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
    """The innermost cause's message: draccus wraps a config's ValueError in a ParsingError, and the innermost
    error is the one that says what to change."""
    while err.__cause__ is not None:
        err = err.__cause__
    return str(err)
