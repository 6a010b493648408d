"""The repository stands on its own: no tracked file refers to a document or folder outside it.

Background notes that lived beside the checkout (a design note, reference notes, a shared fixtures folder) were
written into docs/ (docs/CONVENTIONS.md, docs/OFFICIAL_OPENFLY.md, docs/METRICS.md) and tests/fixtures/; a
citation of the old files, or a relative link that leaves the repository, fails here with the file and line.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# Written in pieces so that this file does not match itself.
OUTSIDE = re.compile(
    "|".join(
        [
            r"\.\./" + "shared",
            "DESIGN" + r"\.md",
            "STYLE" + r"\.md",
            "reference/" + r"(openfly|peers|environment)\.md",
            "shared/" + "fixtures",
            r"\breference \d+\.\d+",  # a section of the old reference notes ("reference 1.2")
        ]
    )
)
MARKDOWN_LINK = re.compile(r"\]\(([^)\s]+)\)")
TEXT_SUFFIXES = {".py", ".md", ".yaml", ".yml", ".toml", ".sh", ".txt", ".cfg", ".json", ".jsonl", ""}


def tracked_files() -> list[Path]:
    """The repository's files (tracked or not ignored) from git when it is a checkout, else every file outside ignored folders."""
    try:
        listed = subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=REPO,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.split("\0")
        return [REPO / name for name in listed if name and (REPO / name).is_file()]
    except (OSError, subprocess.CalledProcessError):
        skip = {".git", ".venv", "outputs", "__pycache__", ".pytest_cache", ".ruff_cache"}
        return [p for p in REPO.rglob("*") if p.is_file() and not skip & set(p.relative_to(REPO).parts)]


def outside_references(path: Path) -> list[str]:
    """`file:line: text` for each line of `path` that names a path outside the repository."""
    if path.suffix not in TEXT_SUFFIXES or path.stat().st_size > 2_000_000:
        return []
    try:
        lines = path.read_text().splitlines()
    except UnicodeDecodeError:
        return []
    where = path.relative_to(REPO)
    found = [f"{where}:{n}: {line.strip()}" for n, line in enumerate(lines, 1) if OUTSIDE.search(line)]
    if path.suffix == ".md":  # relative links must stay inside the repository
        for n, line in enumerate(lines, 1):
            for target in MARKDOWN_LINK.findall(line):
                if re.match(r"[a-z]+:", target) or target.startswith("#"):
                    continue
                resolved = (path.parent / target.split("#")[0]).resolve()
                if not resolved.is_relative_to(REPO):
                    found.append(f"{where}:{n}: link {target} leaves the repository")
    return found


def test_no_file_refers_to_a_path_outside_the_repository():
    files = tracked_files()
    assert len(files) > 100 and REPO / "README.md" in files
    found = [line for path in files if path != Path(__file__).resolve() for line in outside_references(path)]
    assert not found, "\n".join(found)


def test_a_citation_of_an_outside_document_is_caught(tmp_path, monkeypatch):
    monkeypatch.setattr("test_self_contained.REPO", tmp_path)
    for text in ["World frame of " + "DESIGN.md.", "see ../" + "shared/x", "[a](../../outside.md)"]:
        doc = tmp_path / "doc.md"
        doc.write_text(f"fine\n{text}\n")
        assert [line.split(":")[1] for line in outside_references(doc)] == ["2"], text
    (tmp_path / "doc.md").write_text("[conventions](docs/CONVENTIONS.md) and reference/other.md\n")
    assert outside_references(tmp_path / "doc.md") == []
