"""utils/files.py: the atomic file write of the dataset, evaluation and metrics writers."""

from __future__ import annotations

import json

import pytest

from openfly_agent.data.writer import write_json_atomic
from openfly_agent.utils.files import write_atomic


def test_write_atomic_writes_the_file_and_leaves_nothing_beside_it(tmp_path):
    path = tmp_path / "sub" / "a.json"  # the folder is created
    write_atomic(path, lambda tmp: tmp.write_text("new"))
    assert path.read_text() == "new"
    assert sorted(p.name for p in path.parent.iterdir()) == ["a.json"]


def test_a_failing_write_keeps_the_old_file_and_removes_its_temporary(tmp_path):
    path = tmp_path / "a.json"
    path.write_text("old")

    def fail(tmp):
        tmp.write_text("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_atomic(path, fail)
    assert path.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]


def test_a_second_writer_of_the_same_file_in_the_middle_of_a_write_breaks_neither(tmp_path):
    """Two runs finalizing one shared dataset write the same annotation file at once. Each writer has its own
    temporary file, so both renames succeed and the last one wins (a shared temporary name made the first
    rename fail with FileNotFoundError)."""
    path = tmp_path / "train.json"

    def first(tmp):
        tmp.write_text("first")
        write_atomic(path, lambda other: other.write_text("second"))  # the other process, mid-write

    write_atomic(path, first)
    assert path.read_text() == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["train.json"]


def test_write_json_atomic_round_trips(tmp_path):
    records = [{"image_path": "a/b", "gpt_instruction": "fly to the red tower"}]
    write_json_atomic(tmp_path / "Annotation" / "train.json", records)
    assert json.loads((tmp_path / "Annotation" / "train.json").read_text()) == records
