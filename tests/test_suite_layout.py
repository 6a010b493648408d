"""The test suite itself: pytest imports each test file by its base name (the tests folders are not packages), so
two files of one name in two folders stop the whole collection ("import file mismatch")."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def test_every_test_file_has_a_name_of_its_own():
    folders = defaultdict(list)
    for path in sorted(TESTS.rglob("test_*.py")):
        if "__pycache__" not in path.parts:
            folders[path.name].append(str(path.parent.relative_to(TESTS)))
    clashes = {name: where for name, where in folders.items() if len(where) > 1}
    assert not clashes, (
        f"test files sharing a name (prefix them with their folder, test_<folder>_...): {clashes}"
    )
