"""Tables from episode records: per-scene and overall metrics for every profile, as JSON and Markdown.

Everything here is a pure function of the records (the JSONL log), so a table printed at the end of a
run and one recomputed later from the log are the same.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict

from openfly_agent.eval.metrics import EpisodeTrajectory, aggregate, episode_metrics
from openfly_agent.eval.profiles import get_profile
from openfly_agent.rollout.record import EpisodeRecord

RESULTS_VERSION = 1
# (summary key, column title, decimals)
COLUMNS = (
    ("episodes", "Episodes", 0),
    ("errors", "Errors", 0),
    ("ne_m", "NE (m)", 1),
    ("sr_pct", "SR (%)", 1),
    ("osr_pct", "OSR (%)", 1),
    ("spl_pct", "SPL (%)", 1),
    ("ndtw_pct", "nDTW (%)", 1),
    ("collision_rate_pct", "Coll. (%)", 1),
    ("stop_rate_pct", "Stop (%)", 1),
)
# Where the episodes end (`eval.metrics.OUTCOMES`; the rates of a row sum to 100).
OUTCOME_COLUMNS = (
    ("episodes", "Episodes", 0),
    ("sr_pct", "Success (%)", 1),
    ("stopped_far_pct", "STOP, never within radius (%)", 1),
    ("stopped_after_passing_pct", "STOP after passing within (%)", 1),
    ("collision_end_pct", "Collision end (%)", 1),
    ("step_limit_pct", "Step limit (%)", 1),
)


def trajectory_of(record: EpisodeRecord) -> EpisodeTrajectory:
    """The metrics' view of a record: visited positions, STOP, collisions, goal and reference path."""
    return EpisodeTrajectory(
        episode_id=record.episode_id,
        scene_id=record.scene_id,
        positions=record.positions(),
        goal=record.goal,
        reference_path=record.reference_path,
        stopped=record.stopped,
        stop_step=record.stop_step,
        collision_steps=tuple(record.collision_steps),
    )


def episode_rows(records: Sequence[EpisodeRecord], profile: str) -> list[dict]:
    """`episode_metrics` of every record under `profile`, with the split added."""
    rows = []
    for record in records:
        row = episode_metrics(trajectory_of(record), profile)
        row["split"] = record.split
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
    scored = [r for r in records if not r.errored]
    if scored:
        table = aggregate(episode_rows(scored, profile), by="scene")
    else:  # every episode failed: nothing to average
        table = {"profile": profile, "overall": {"episodes": 0}, "per_scene": {}}
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
    "splits": {split: {profile: {"profile", "overall", "per_scene", "scene_mean"}}}, "errors": {split: n}}
    with the summary keys of `eval.metrics.aggregate` (`ne_m`, `sr_pct`, `osr_pct`, `spl_pct`, ...) plus
    `errors`, the episodes that ended in an engine error and are left out of every metric.
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


def _fmt(value: float, decimals: int) -> str:
    return f"{value:.{decimals}f}" if decimals else str(int(round(value)))


def _row(name: str, summary: dict, columns: Sequence[tuple] = COLUMNS) -> str:
    cells = [_fmt(summary[key], d) if key in summary else "" for key, _, d in columns]
    return "| " + " | ".join([name, *cells]) + " |"


def _header(first: str, columns: Sequence[tuple] = COLUMNS) -> list[str]:
    titles = [first, *(title for _, title, _ in columns)]
    return ["| " + " | ".join(titles) + " |", "|" + "|".join(["---"] + ["---:"] * len(columns)) + "|"]


def results_markdown(results: dict) -> str:
    """Per-scene and overall Markdown tables of one policy's results, one per split and profile."""
    lines = [f"# Closed-loop results: {results['policy']}", ""]
    outcomes = ["## Where the episodes end", "", *_header("Split / profile", OUTCOME_COLUMNS)]
    for split, by_profile in results["splits"].items():
        for profile, table in by_profile.items():
            lines += [f"## {split} - profile `{profile}`", "", *_header("Scene")]
            lines += [_row(scene, summary) for scene, summary in table.get("per_scene", {}).items()]
            if "scene_mean" in table:
                scene_mean = dict(table["scene_mean"], episodes=table["overall"]["episodes"])
                lines.append(_row("**scene mean**", scene_mean))
            lines += [_row("**overall**", table["overall"]), ""]
            outcomes.append(_row(f"{split} / `{profile}`", table["overall"], OUTCOME_COLUMNS))
    return "\n".join(lines + outcomes + [""])


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
            lines += [f"### {split} - profile `{profile}`", "", *_header("Policy")]
            for results in all_results:
                table = results["splits"].get(split, {}).get(profile)
                if table is not None:
                    lines.append(_row(results["policy"], table["overall"]))
            lines.append("")
    return "\n".join(lines)
