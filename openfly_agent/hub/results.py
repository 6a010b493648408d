"""Read eval.py's results JSON into the overall NE / SR / OSR / SPL of each split x metric profile."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from openfly_agent.constants import MEMORY_PROBE_NONE, RESULTS_JSON, SPLIT_TEST_SEEN, SPLIT_TEST_UNSEEN
from openfly_agent.rollout.metrics import INTERVAL_KEYS
from openfly_agent.rollout.stats import wilson_interval

PROFILES = ("openfly", "standard")
RELEASE_SPLITS = (SPLIT_TEST_SEEN, SPLIT_TEST_UNSEEN)
AGENT_POLICY = "agent"
# card metric -> key of eval's overall summary (units in the key: metres, percent)
METRIC_KEYS = {"NE": "ne_m", "SR": "sr_pct", "OSR": "osr_pct", "SPL": "spl_pct"}
RATE_METRICS = ("SR", "OSR")  # an interval of these can be recomputed from the rate and the episodes


class ResultsError(ValueError):
    """The results JSON lacks a split, profile or metric the card needs; the message names file and key."""


@dataclass(frozen=True)
class ResultRow:
    """Overall metrics of one split under one metric profile (NE in metres, the rest in percent)."""

    split: str
    profile: str
    metrics: dict[str, float]
    num_episodes: int | None = None
    # the split's episodes when `num_episodes` is a subsample (max_episodes)
    split_episodes: int | None = None
    # card metric -> its 95 % interval (eval's `<metric>_ci95`; for SR / OSR of results written before eval
    # recorded intervals, the Wilson interval of round(rate * episodes / 100) of the episodes)
    intervals: dict[str, tuple[float, float]] = field(default_factory=dict)
    successes: int | None = None  # episodes that succeeded (None: unknown)


@dataclass(frozen=True)
class EvalResults:
    """The rows the card reports plus the run facts stored beside them."""

    rows: list[ResultRow]
    profiles: dict[str, dict[str, Any]] = field(default_factory=dict)  # profile name -> its settings
    meta: dict[str, Any] = field(default_factory=dict)  # checkpoint, sim, dataset root, max steps, ...
    source: str = ""
    policy: str = AGENT_POLICY

    @property
    def subsampled(self) -> bool:
        """Whether the numbers cover only part of a split (`--max_episodes`)."""
        return any(row.split_episodes is not None for row in self.rows)


def resolve_results_path(path: str | Path) -> Path:
    """`path` itself, or `<path>/agent/results.json` when `path` is an eval output folder."""
    path = Path(path)
    if path.is_dir():
        candidate = path / AGENT_POLICY / RESULTS_JSON
        if not candidate.is_file():
            raise ResultsError(
                f"{path} is a folder without {AGENT_POLICY}/{RESULTS_JSON}: pass the results file"
            )
        return candidate
    return path


def load_results(path: str | Path) -> EvalResults:
    """Read eval.py's `results.json` (file, or the eval output folder holding `agent/results.json`).

    Shape (eval/report.py `policy_results`)::

        {"version": 1, "policy": "agent", "meta": {...}, "profiles": {"openfly": {...}, ...},
         "splits": {"test_seen": {"openfly": {"overall": {"episodes": 40, "ne_m": 31.2, "sr_pct": 12.5,
                                                          "osr_pct": 20.0, "spl_pct": 11.0, ...}, ...}}}}

    Raises:
        ResultsError: not JSON, results of a baseline or of a memory probe (a diagnostic), episodes that ended
            in an engine error (not scored),
            results of one split only (a release reports both RELEASE_SPLITS), or a profile / metric missing or
            not finite.
    """
    path = resolve_results_path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ResultsError(f"{path}: cannot read the eval results JSON ({err})") from err
    return parse_results(data, source=str(path))


def parse_results(data: dict[str, Any], source: str = "<results>", policy: str = AGENT_POLICY) -> EvalResults:
    """`load_results` on an already parsed dict; `source` names it in errors, `policy` is the one expected."""
    found = data.get("policy", AGENT_POLICY) if isinstance(data, dict) else AGENT_POLICY
    if found != policy:
        wanted = f"the agent ('{AGENT_POLICY}')" if policy == AGENT_POLICY else repr(policy)
        raise ResultsError(f"{source}: holds results of policy {found!r}, not of {wanted}")
    errored = {split: n for split, n in (data.get("errors") or {}).items() if n}
    if errored:
        raise ResultsError(
            f"{source}: {sum(errored.values())} episodes ended in an engine error and were not scored "
            f"({errored}); run the same eval.py command again to retry them before releasing"
        )
    splits = _child(data, "splits", source, "")
    held = sorted(splits) if isinstance(splits, dict) else []
    if any(split not in held for split in RELEASE_SPLITS):
        raise ResultsError(
            f"{source} holds results of {' and '.join(held) or 'no split'} only; a release needs both "
            f"{' and '.join(RELEASE_SPLITS)}: evaluate with eval.py --split=[{','.join(RELEASE_SPLITS)}] "
            "(into the same --output_dir, the episodes already done are kept)"
        )
    meta = dict(data.get("meta") or {})
    probe = meta.get("memory_probe")
    if probe not in (None, MEMORY_PROBE_NONE):
        raise ResultsError(
            f"{source}: results of the memory probe agent.memory_probe={probe}, a diagnostic, not the model as "
            "trained; release the results of an eval.py run without the probe"
        )
    split_sizes = meta.get("split_episodes") or {}
    rows = []
    for split in RELEASE_SPLITS:
        by_profile = _child(splits, split, source, "splits")
        for profile in PROFILES:
            where = f"splits.{split}.{profile}"
            overall = _child(_child(by_profile, profile, source, f"splits.{split}"), "overall", source, where)
            metrics = {
                name: _number(overall, key, source, f"{where}.overall") for name, key in METRIC_KEYS.items()
            }
            count = overall.get("episodes")
            count = int(count) if count is not None else None
            total = split_sizes.get(split)
            part = total if count is not None and total is not None and count < total else None
            intervals = _intervals(overall, metrics, count, source, f"{where}.overall")
            successes = overall.get("successes")
            if successes is None and count:
                successes = round(metrics["SR"] * count / 100.0)
            rows.append(ResultRow(split, profile, metrics, count, part, intervals, successes))
    return EvalResults(rows, dict(data.get("profiles") or {}), meta, source, policy)


def _intervals(
    overall: dict, metrics: dict[str, float], count: int | None, source: str, where: str
) -> dict[str, tuple[float, float]]:
    """The 95 % interval of each card metric that has one (`ResultRow.intervals`)."""
    intervals = {}
    for name, key in METRIC_KEYS.items():
        interval_key = INTERVAL_KEYS[key]
        if interval_key in overall:
            value = overall[interval_key]
            finite = all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                for v in (value if isinstance(value, list) else [])
            )
            if not (isinstance(value, list) and len(value) == 2 and finite):
                raise ResultsError(
                    f"{source}: '{where}.{interval_key}' = {value!r} is not a [low, high] pair"
                )
            intervals[name] = (float(value[0]), float(value[1]))
        elif name in RATE_METRICS and count:
            low, high = wilson_interval(min(count, max(0, round(metrics[name] * count / 100.0))), count)
            intervals[name] = (100.0 * low, 100.0 * high)
    return intervals


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
