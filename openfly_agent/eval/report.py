"""Tables from episode records: per-scene and overall metrics for every profile, as JSON and Markdown.

Everything here is a pure function of the records (the JSONL log), so a table printed at the end of a
run and one recomputed later from the log are the same.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, replace

import numpy as np

from openfly_agent.data.records import parse_episode_id
from openfly_agent.rollout.metrics import (
    EARLY_STOP_STEPS,
    INTERVAL_KEYS,
    aggregate,
    episode_metrics,
    trajectory_of,
)
from openfly_agent.rollout.profiles import get_profile
from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.rollout.stats import BOOTSTRAP_RESAMPLES, BOOTSTRAP_SEED, format_interval

RESULTS_VERSION = 2  # 2 added the counts, the 95 % intervals and the breakdowns
# (summary key, column title, decimals); "successes" prints "k of n", a key of `INTERVAL_KEYS` its interval
COLUMNS = (
    ("episodes", "Episodes", 0),
    ("errors", "Errors", 0),
    ("successes", "Successes", 0),
    ("ne_m", "NE (m)", 1),
    ("sr_pct", "SR (%)", 1),
    ("osr_pct", "OSR (%)", 1),
    ("spl_pct", "SPL (%)", 1),
    ("ndtw_pct", "nDTW (%)", 1),
    ("collision_rate_pct", "Coll. (%)", 1),
    ("stop_rate_pct", "Stop (%)", 1),
)
BREAKDOWN_COLUMNS = tuple(
    c for c in COLUMNS if c[0] in ("episodes", "successes", "ne_m", "sr_pct", "osr_pct", "spl_pct")
)
# Where the episodes end (`rollout.metrics.OUTCOMES`; the rates of a row sum to 100).
OUTCOME_COLUMNS = (
    ("episodes", "Episodes", 0),
    ("sr_pct", "Success (%)", 1),
    ("early_stop_pct", "Early STOP (%)", 1),
    ("stopped_far_pct", "STOP, never within radius (%)", 1),
    ("stopped_after_passing_pct", "STOP after passing within (%)", 1),
    ("collision_end_pct", "Collision end (%)", 1),
    ("step_limit_pct", "Step limit (%)", 1),
)
# Breakdowns of every split and profile: row key -> (title, its groups in table order). The route length and
# flight height come from the category in the episode id (`<scene>/astar_data/<height>_<length>[_updown]/...`,
# docs/TOOLCHAIN.md "Categories"; "unknown" for other ids), the start distance is the straight 3-D start-goal one.
START_DISTANCE_BINS_M = (50, 100, 150, 200)
UNKNOWN = "unknown"
BREAKDOWNS = {
    "route_length": ("Route length", ("short", "average", "long", UNKNOWN)),
    "flight_height": ("Flight height", ("low", "medium", "high", UNKNOWN)),
    "start_distance": (
        "Start-goal distance",
        (
            f"< {START_DISTANCE_BINS_M[0]} m",
            *(f"{a}-{b} m" for a, b in zip(START_DISTANCE_BINS_M, START_DISTANCE_BINS_M[1:])),
            f">= {START_DISTANCE_BINS_M[-1]} m",
        ),
    ),
}
INTERVAL_NOTE = (
    "Numbers in brackets are 95 % intervals: Wilson score intervals for SR and OSR, a percentile bootstrap over "
    f"the episodes ({BOOTSTRAP_RESAMPLES:,} resamples, seed {BOOTSTRAP_SEED}) for SPL and NE (docs/METRICS.md). "
    f"Early STOP: a failed STOP among the first {EARLY_STOP_STEPS} actions."
)
# What `scored` keeps of each profile's `episode_metrics` in the record (EpisodeRecord.metrics).
RECORD_METRIC_KEYS = ("success", "ne", "oracle_success", "spl", "outcome")


def scored(record: EpisodeRecord, profiles: Sequence[str]) -> EpisodeRecord:
    """A copy of `record` with its `metrics` filled: `RECORD_METRIC_KEYS` of `episode_metrics` per profile (an
    engine error is not scored: unchanged)."""
    if record.errored:
        return record
    trajectory = trajectory_of(record)
    metrics = {}
    for profile in profiles:
        row = episode_metrics(trajectory, profile)
        metrics[profile] = {key: row[key] for key in RECORD_METRIC_KEYS}
    return replace(record, metrics=metrics)


def route_class(episode_id: str) -> tuple[str, str]:
    """(route length, flight height) of an episode from the category in its id (`UNKNOWN` where it has none)."""
    _, category = parse_episode_id(episode_id)
    parts = category.split("_")
    length_names, height_names = BREAKDOWNS["route_length"][1], BREAKDOWNS["flight_height"][1]
    height = parts[0] if parts[0] in height_names else UNKNOWN
    length = parts[1] if len(parts) > 1 and parts[1] in length_names else UNKNOWN
    return length, height


def start_distance_bin(record: EpisodeRecord) -> str:
    """The `START_DISTANCE_BINS_M` bin of the straight 3-D distance from the start to the goal."""
    distance = float(np.linalg.norm(record.positions()[0] - np.asarray(record.goal, dtype=np.float64)))
    index = int(np.searchsorted(START_DISTANCE_BINS_M, distance, side="right"))
    return BREAKDOWNS["start_distance"][1][index]


def episode_rows(records: Sequence[EpisodeRecord], profile: str) -> list[dict]:
    """`episode_metrics` of every record under `profile`, with the split and the `BREAKDOWNS` keys added."""
    rows = []
    for record in records:
        row = episode_metrics(trajectory_of(record), profile)
        row["split"] = record.split
        row["route_length"], row["flight_height"] = route_class(record.episode_id)
        row["start_distance"] = start_distance_bin(record)
        rows.append(row)
    return rows


def split_tables(records: Sequence[EpisodeRecord], profiles: Sequence[str]) -> dict[str, dict[str, dict]]:
    """{split: {profile: aggregate by scene}} over `records` (splits in order of first appearance).

    Episodes that ended in an engine error are not scored: the metrics cover the others, and `errors` (in
    `overall` and per scene) counts them.
    """
    splits = list(dict.fromkeys(r.split for r in records))
    tables: dict[str, dict[str, dict]] = {}
    for split in splits:
        subset = [r for r in records if r.split == split]
        tables[split] = {p: _profile_table(subset, p) for p in profiles}
    return tables


def _profile_table(records: Sequence[EpisodeRecord], profile: str) -> dict:
    finished = [r for r in records if not r.errored]
    if finished:
        rows = episode_rows(finished, profile)
        table = aggregate(rows, by="scene")
        table["breakdowns"] = {}
        for by, (_, order) in BREAKDOWNS.items():
            groups = aggregate(rows, by=by)[f"per_{by}"]
            table["breakdowns"][by] = {name: groups[name] for name in order if name in groups}
    else:  # every episode failed: nothing to average
        table = {"profile": profile, "overall": {"episodes": 0}, "per_scene": {}, "breakdowns": {}}
    errors_by_scene: dict[str, int] = {}
    for record in records:
        if record.errored:
            errors_by_scene[record.scene_id] = errors_by_scene.get(record.scene_id, 0) + 1
    table["overall"]["errors"] = sum(errors_by_scene.values())
    for scene in sorted(set(errors_by_scene) | set(table["per_scene"])):
        table["per_scene"].setdefault(scene, {"episodes": 0})["errors"] = errors_by_scene.get(scene, 0)
    table["per_scene"] = dict(sorted(table["per_scene"].items()))
    return table


def policy_results(
    policy: str, records: Sequence[EpisodeRecord], profiles: Sequence[str], meta: dict | None = None
) -> dict:
    """The `results.json` of one policy.

    Shape: {"version", "policy", "meta": {...}, "profiles": {name: profile fields},
    "splits": {split: {profile: {"profile", "overall", "per_scene", "scene_mean", "breakdowns"}}},
    "errors": {split: n}} with the summary keys of `rollout.metrics.aggregate` (`ne_m`, `sr_pct`, `osr_pct`,
    `spl_pct`, ..., `successes`, `sr_ci95`, ...) plus `errors`, the episodes that ended in an engine error and
    are left out of every metric; `breakdowns` holds {by: {group: summary}} for each of `BREAKDOWNS`.
    """
    return {
        "version": RESULTS_VERSION,
        "policy": policy,
        "meta": dict(meta or {}),
        "profiles": {p: asdict(get_profile(p)) for p in profiles},
        "splits": split_tables(records, profiles),
        "errors": {
            split: sum(r.errored for r in records if r.split == split)
            for split in dict.fromkeys(r.split for r in records)
        },
    }


def _cell(summary: dict, key: str, decimals: int) -> str:
    """One table cell: "k of n" for the successes, a number with its 95 % interval where the summary holds one."""
    if key not in summary:
        return ""
    if key == "successes":
        return f"{summary[key]} of {summary['episodes']}"
    if not decimals:
        return str(int(round(summary[key])))
    return format_interval(summary[key], summary.get(INTERVAL_KEYS.get(key, "")), decimals)


def _row(name: str, summary: dict, columns: Sequence[tuple] = COLUMNS) -> str:
    cells = [_cell(summary, key, d) for key, _, d in columns]
    return "| " + " | ".join([name, *cells]) + " |"


def _header(first: str, columns: Sequence[tuple] = COLUMNS) -> list[str]:
    titles = [first, *(title for _, title, _ in columns)]
    return ["| " + " | ".join(titles) + " |", "|" + "|".join(["---"] + ["---:"] * len(columns)) + "|"]


def results_markdown(results: dict) -> str:
    """Per-scene and overall Markdown tables of one policy's results, one per split and profile."""
    lines = [f"# Closed-loop results: {results['policy']}", "", INTERVAL_NOTE, ""]
    outcomes = ["## Where the episodes end", "", *_header("Split / profile", OUTCOME_COLUMNS)]
    for split, by_profile in results["splits"].items():
        for profile, table in by_profile.items():
            lines += [f"## {split} - profile `{profile}`", ""]
            note = subsample_note(results, split)
            lines += [note, ""] if note else []
            lines += _header("Scene")
            lines += [_row(scene, summary) for scene, summary in table.get("per_scene", {}).items()]
            if "scene_mean" in table:
                scene_mean = dict(table["scene_mean"], episodes=table["overall"]["episodes"])
                lines.append(_row("**scene mean**", scene_mean))
            lines += [_row("**overall**", table["overall"]), ""]
            for by, groups in table.get("breakdowns", {}).items():
                title = BREAKDOWNS[by][0] if by in BREAKDOWNS else by
                lines += [
                    f"### {split} - `{profile}` by {title.lower()}",
                    "",
                    *_header(title, BREAKDOWN_COLUMNS),
                ]
                lines += [_row(group, summary, BREAKDOWN_COLUMNS) for group, summary in groups.items()]
                lines.append("")
            outcomes.append(_row(f"{split} / `{profile}`", table["overall"], OUTCOME_COLUMNS))
    return "\n".join(lines + outcomes + [""])


def subsample_note(results: dict, split: str) -> str | None:
    """`Evaluated 20 of the split's 260 episodes (max_episodes).` when the run covered only part of `split`."""
    total = (results.get("meta") or {}).get("split_episodes", {}).get(split)
    counts = [
        t["overall"]["episodes"] + t["overall"].get("errors", 0) for t in results["splits"][split].values()
    ]
    if total is None or not counts or counts[0] >= total:
        return None
    return f"Evaluated {counts[0]} of the split's {total} episodes (`max_episodes`)."


def _splits_of(all_results: Sequence[dict]) -> list[str]:
    """Every split of the policies' results, in order of first appearance."""
    return list(dict.fromkeys(s for r in all_results for s in r["splits"]))


def outcomes_markdown(all_results: Sequence[dict], profiles: Sequence[str]) -> str:
    """One table per split of where each policy's episodes end, a row per policy and profile."""
    lines = []
    for split in _splits_of(all_results):
        lines += [f"### {split} - where the episodes end", "", *_header("Policy / profile", OUTCOME_COLUMNS)]
        for results in all_results:
            for profile in profiles:
                table = results["splits"].get(split, {}).get(profile)
                if table is not None:
                    name = f"{results['policy']} / `{profile}`"
                    lines.append(_row(name, table["overall"], OUTCOME_COLUMNS))
        lines.append("")
    return "\n".join(lines)


def comparison_markdown(all_results: Sequence[dict], profiles: Sequence[str]) -> str:
    """One table per split and profile with a row per policy (overall, episode-weighted means)."""
    lines = []
    for split in _splits_of(all_results):
        for profile in profiles:
            lines += [f"### {split} - profile `{profile}`", ""]
            notes = {subsample_note(r, split) for r in all_results if split in r["splits"]} - {None}
            lines += [*sorted(notes), ""] if notes else []
            lines += _header("Policy")
            for results in all_results:
                table = results["splits"].get(split, {}).get(profile)
                if table is not None:
                    lines.append(_row(results["policy"], table["overall"]))
            lines.append("")
    return "\n".join(lines)
