"""Read eval.py's results JSON into the overall NE / SR / OSR / SPL of each split x metric profile."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from openfly_agent.constants import SPLIT_TEST_SEEN, SPLIT_TEST_UNSEEN

PROFILES = ("openfly", "standard")
RELEASE_SPLITS = (SPLIT_TEST_SEEN, SPLIT_TEST_UNSEEN)
# metric key in the results JSON -> (unit, pretty name)
METRICS: dict[str, tuple[str, str]] = {
    "NE": ("m", "Navigation error"),
    "SR": ("%", "Success rate"),
    "OSR": ("%", "Oracle success rate"),
    "SPL": ("%", "Success weighted by path length"),
}


class ResultsError(ValueError):
    """The results JSON lacks a split, profile or metric the card needs; the message names file and key."""


@dataclass(frozen=True)
class ResultRow:
    """Overall metrics of one split under one metric profile (NE in metres, the rest in percent)."""

    split: str
    profile: str
    metrics: dict[str, float]
    num_episodes: int | None = None


def load_results(path: str | Path) -> list[ResultRow]:
    """Read a results JSON and return one row per (split, profile) for test_seen / test_unseen.

    Expected shape (eval.py, docs/RELEASE.md)::

        {"splits": {"test_seen": {"profiles": {"openfly": {"overall": {
            "NE": 31.2, "SR": 12.5, "OSR": 20.0, "SPL": 11.0, "num_episodes": 40}}, ...}}}}

    Raises:
        ResultsError: the file is not JSON, or a split / profile / metric is missing or not a finite number.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ResultsError(f"{path}: cannot read the eval results JSON ({err})") from err
    return parse_results(data, source=str(path))


def parse_results(data: dict[str, Any], source: str = "<results>") -> list[ResultRow]:
    """`load_results` on an already parsed dict; `source` names it in errors."""
    splits = _child(data, "splits", source, "")
    rows = []
    for split in RELEASE_SPLITS:
        split_data = _child(splits, split, source, "splits")
        profiles = _child(split_data, "profiles", source, f"splits.{split}")
        for profile in PROFILES:
            where = f"splits.{split}.profiles.{profile}"
            overall = _child(
                _child(profiles, profile, source, where.rsplit(".", 1)[0]), "overall", source, where
            )
            metrics = {name: _number(overall, name, source, f"{where}.overall") for name in METRICS}
            count = overall.get("num_episodes")
            rows.append(ResultRow(split, profile, metrics, int(count) if count is not None else None))
    return rows


def _child(node: Any, key: str, source: str, where: str) -> Any:
    if not isinstance(node, dict) or key not in node:
        found = sorted(node) if isinstance(node, dict) else type(node).__name__
        raise ResultsError(f"{source}: missing key '{where + '.' if where else ''}{key}' (found {found})")
    return node[key]


def _number(node: dict, key: str, source: str, where: str) -> float:
    value = _child(node, key, source, where)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ResultsError(f"{source}: '{where}.{key}' = {value!r} is not a finite number")
    return float(value)
