"""The figures of finished recipe runs side by side: one row per run (an ablation arm), as markdown or a dict.

Read from what the recipe wrote and finished (a folder with the recipe's completion marker), nothing is
recomputed: the navigation stage's `logs/metrics.jsonl` (its last step), the evaluated agent's (the last DAgger
round's training the recipe finished, else the navigation stage's: its last test-split evaluation),
`eval/summary.json` (the agent on the main test splits) and each `eval-<cities>/summary.json` (the agent on the
test_unseen split of more unseen cities). `read_runs` also pairs each run's agent with the first run's (the
reference arm) episode by episode on the main test splits (eval/compare.py), so every row carries its SR difference
from the reference with a 95 % interval and an exact McNemar p. A folder without the marker, e.g. an earlier round's agent evaluated
by hand into the run folder or a round trained by hand, is not the recipe's and is left out; a main evaluation
without it is refused, as is an evaluation with failed episodes: a failure is never a result.
After an RL stage the evaluated agent is its (`rl/`, with the offline figures of the agent it started from: the
stage runs no offline test), and `rl_comparison` pairs it with that agent (`eval_before_rl/` and each
`eval_before_rl-<cities>/`) on the same episodes.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.eval.compare import (
    compare_folders,
    compare_split,
    comparison_markdown,
    interval,
    p_value,
    paired_records,
    signed,
)
from openfly_agent.eval.config import PROFILE_NAMES
from openfly_agent.eval.outputs import SUMMARY_JSON
from openfly_agent.recipe.run import DONE_MARKER, EVAL_BEFORE_RL_DIR, RL_DIR, step_finished
from openfly_agent.rollout.stats import format_interval, wilson_interval
from openfly_agent.training.accelerator import LOGS_DIR
from openfly_agent.training.trackers import METRICS_FILE_NAME, read_metrics

AGENT = "agent"
AGENT_BEFORE_RL = "agent_before_rl"  # the report's name of the agent the RL stage started from
PROFILE_STANDARD, PROFILE_OPENFLY = "standard", "openfly"
ALL_UNSEEN = "all unseen"  # rl_comparison's pooled split: test_unseen and the more cities' test_unseen


@dataclass
class RunFigures:
    """One recipe run's headline figures (percentages as in eval's summary.json)."""

    name: str
    navigation_steps: int  # optimizer steps the navigation stage ran
    # the training run of the evaluated agent: "navigation", "dagger/r<k>/train" or "rl"
    final_stage: str
    # the last test-split action accuracy of the evaluated agent's supervised stage (after an RL stage: of the
    # agent it started from; the RL stage runs no offline test)
    offline_accuracy: float | None
    offline_box_iou: float | None  # ... and target-box IoU (None: a run without a grounding head)
    sr: dict[str, float]  # split -> SR (%), standard profile
    sr_openfly: dict[str, float]  # split -> SR (%), openfly profile
    collisions_unseen: float | None  # test_unseen, standard profile
    stopped_unseen: float | None
    # the test_unseen split of each eval.more_cities dataset: name -> (SR %, episodes)
    more_cities: dict[str, tuple[float, int]] = field(default_factory=dict)
    all_unseen_sr: float | None = None  # SR over every test_unseen episode (main split + more cities)
    all_unseen_episodes: int = 0
    episodes: dict[str, int] = field(default_factory=dict)  # split -> scored episodes (the SR's n)
    # the agent against the reference run's on the same episodes (standard profile), per main test split:
    # {"reference", "sr_diff_pp", "sr_diff_ci_pp", "mcnemar_p", "counts"}; empty for the reference itself
    vs_reference: dict[str, dict] = field(default_factory=dict)


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing (has the recipe run finished this step?)")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from err


def _training_figures(run: Path) -> tuple[int, float | None, float | None]:
    """(last step, last test action accuracy, last test box IoU) of a training run folder's metrics."""
    logs = run / LOGS_DIR
    records = read_metrics(logs)
    if not records:
        raise FileNotFoundError(
            f"{logs / METRICS_FILE_NAME}: missing or empty (has this stage of the recipe finished?)"
        )
    step, accuracy, iou = 0, None, None
    for record in records:
        step = max(step, int(record.get("step", 0)))
        if "test/action_accuracy" in record:
            accuracy, iou = record["test/action_accuracy"], _measured(record.get("test/box_iou"))
    if not _has_grounding_head(run):  # runs logged before the agent wrote NaN there had a 0.0: not an IoU
        iou = None
    return step, accuracy, iou


def _measured(value) -> float | None:
    """A logged figure, or None where nothing was measured (missing, or NaN, which the metrics file writes "nan")."""
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _has_grounding_head(run: Path) -> bool:
    """Whether the training run's saved config has a grounding head (True where it does not say)."""
    path = run / C.TRAIN_CONFIG_NAME
    if not path.is_file():
        return True
    grounding = _read_json(path).get("model", {}).get("grounding", {})
    return bool(grounding.get("enabled", True))


def _agent_split(summary: dict, path: Path, split: str, profile: str) -> dict:
    """The agent's figures on one split and profile of an eval summary.json; refuses failed episodes."""
    try:
        figures = summary[AGENT][split][profile]
    except KeyError as err:
        raise ValueError(f"{path}: no {AGENT} / {split} / {profile} figures ({err} missing)") from err
    if figures.get("errors", 0):
        raise ValueError(
            f"{path}: {figures['errors']} of the agent's {split} episodes failed; "
            "re-run that evaluation before tabulating it"
        )
    return figures


def read_run(run_dir: str | Path, name: str | None = None) -> RunFigures:
    """The figures of the finished recipe run in `run_dir` (its navigation/, eval/ and finished eval-*/ folders)."""
    run = Path(run_dir)
    steps, accuracy, iou = _training_figures(run / "navigation")
    final_stage = "navigation"
    rounds = [p for p in run.glob("dagger/r*/train") if step_finished(p)]
    rounds.sort(key=lambda p: int(p.parent.name.removeprefix("r")))
    if rounds:  # the recipe evaluates the last round's agent
        final_stage = rounds[-1].relative_to(run).as_posix()
        _, accuracy, iou = _training_figures(rounds[-1])
    if step_finished(run / RL_DIR):  # the recipe evaluates the RL stage's agent
        final_stage = RL_DIR
    main_path = run / "eval" / SUMMARY_JSON
    if main_path.is_file() and not step_finished(main_path.parent):
        raise ValueError(
            f"{main_path.parent}: the recipe has not finished this evaluation (no {DONE_MARKER}); "
            "resume the recipe before tabulating the run"
        )
    main = _read_json(main_path)
    splits = [s for s in (C.SPLIT_TEST_SEEN, C.SPLIT_TEST_UNSEEN) if s in main.get(AGENT, {})]
    if not splits:
        raise ValueError(f"{main_path}: no test split evaluated for the {AGENT}")
    standard = {s: _agent_split(main, main_path, s, PROFILE_STANDARD) for s in splits}
    openfly = {s: _agent_split(main, main_path, s, PROFILE_OPENFLY) for s in splits}
    unseen = standard.get(C.SPLIT_TEST_UNSEEN)
    figures = RunFigures(
        name=name or run.name,
        navigation_steps=steps,
        final_stage=final_stage,
        offline_accuracy=accuracy,
        offline_box_iou=iou,
        sr={s: f["sr_pct"] for s, f in standard.items()},
        sr_openfly={s: f["sr_pct"] for s, f in openfly.items()},
        collisions_unseen=unseen["collision_rate_pct"] if unseen else None,
        stopped_unseen=unseen["stop_rate_pct"] if unseen else None,
        episodes={s: int(f["episodes"]) for s, f in standard.items()},
    )
    successes, episodes = 0.0, 0
    if unseen:
        successes, episodes = unseen["sr_pct"] * unseen["episodes"] / 100.0, unseen["episodes"]
    for folder in sorted(p for p in run.glob("eval-*") if step_finished(p)):  # the recipe's own evaluations
        path = folder / SUMMARY_JSON
        more = _agent_split(_read_json(path), path, C.SPLIT_TEST_UNSEEN, PROFILE_STANDARD)
        figures.more_cities[path.parent.name.removeprefix("eval-")] = (more["sr_pct"], more["episodes"])
        successes += more["sr_pct"] * more["episodes"] / 100.0
        episodes += more["episodes"]
    if episodes:
        figures.all_unseen_sr, figures.all_unseen_episodes = 100.0 * successes / episodes, episodes
    return figures


def paired_with_reference(run_dir: str | Path, reference_dir: str | Path, reference: str) -> dict[str, dict]:
    """The agent of `run_dir` against the agent of `reference_dir` on the same episodes, per split (standard
    profile): B - A with B this run; a `PairingError` (a ValueError) when they did not fly the same episodes."""
    comparison = compare_folders(
        Path(reference_dir) / "eval" / AGENT, Path(run_dir) / "eval" / AGENT, profiles=[PROFILE_STANDARD]
    )
    keys = ("sr_diff_pp", "sr_diff_ci_pp", "mcnemar_p", "counts")
    return {
        split: {"reference": reference, **{key: by_profile[PROFILE_STANDARD][key] for key in keys}}
        for split, by_profile in comparison["splits"].items()
    }


def rl_comparison(run_dir: str | Path) -> dict | None:
    """The RL stage's agent (B, eval/agent) against the agent it started from (A, eval_before_rl/agent) on the
    same episodes, every figure of `compare_folders`; None unless the recipe finished both evaluations.

    Each more cities' evaluation both agents finished (eval-<cities>/ and eval_before_rl-<cities>/) adds the split
    `test_unseen (<cities>)`, and with one or more of them the split `all unseen` pools their episodes with
    test_unseen's (the recipe's 520 unseen episodes)."""
    run = Path(run_dir)
    before, after = run / EVAL_BEFORE_RL_DIR, run / "eval"
    if not (step_finished(before) and step_finished(after)):
        return None
    comparison = compare_folders(before / AGENT, after / AGENT)
    pooled_a, pooled_b = paired_records(before / AGENT, after / AGENT, C.SPLIT_TEST_UNSEEN)
    cities = 0
    for folder in sorted(run.glob("eval-*")):
        name = folder.name.removeprefix("eval-")
        other = run / f"{EVAL_BEFORE_RL_DIR}-{name}"
        if not (step_finished(folder) and step_finished(other)):
            continue
        records_a, records_b = paired_records(other / AGENT, folder / AGENT, C.SPLIT_TEST_UNSEEN)
        comparison["splits"][f"{C.SPLIT_TEST_UNSEEN} ({name})"] = _compare_profiles(records_a, records_b)
        pooled_a, pooled_b, cities = pooled_a + records_a, pooled_b + records_b, cities + 1
    if cities:
        comparison["splits"][ALL_UNSEEN] = _compare_profiles(pooled_a, pooled_b)
    return comparison


def _compare_profiles(records_a: list, records_b: list) -> dict:
    return {profile: compare_split(records_a, records_b, profile) for profile in PROFILE_NAMES}


def rl_markdown(comparison: dict) -> str:
    """The paired table of `rl_comparison` under a line naming its two sides."""
    cities = ""
    if ALL_UNSEEN in comparison["splits"]:
        cities = (
            f" The rows `{C.SPLIT_TEST_UNSEEN} (<cities>)` pair {EVAL_BEFORE_RL_DIR}-<cities>/{AGENT} with "
            f"eval-<cities>/{AGENT}; `{ALL_UNSEEN}` pools them with {C.SPLIT_TEST_UNSEEN}."
        )
    return (
        f"{AGENT} - {AGENT_BEFORE_RL}: A is {AGENT_BEFORE_RL} (the agent the RL stage started from), B is "
        f"{AGENT} (the RL stage's), flown on the same episodes.{cities}\n\n{comparison_markdown(comparison)}"
    )


def read_runs(named_folders: list[tuple[str, str | Path]]) -> list[RunFigures]:
    """`read_run` of each (name, folder), the first being the reference arm: every other run carries its paired
    SR difference from it (`RunFigures.vs_reference`)."""
    runs = [read_run(folder, name) for name, folder in named_folders]
    if runs:
        reference_name, reference_dir = named_folders[0]
        for run, (_, folder) in zip(runs[1:], named_folders[1:]):
            run.vs_reference = paired_with_reference(folder, reference_dir, reference_name)
    return runs


def _paired(run: RunFigures, split: str) -> str:
    row = run.vs_reference.get(split)
    if row is None:
        return "-"
    return f"{signed(row['sr_diff_pp'])} {interval(row['sr_diff_ci_pp'])}, p {p_value(row['mcnemar_p'])}"


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def _rate(value: float | None, episodes: int | None) -> str:
    """A success rate with the Wilson 95 % interval of its count (round(rate * n / 100) of n), `29.2 (20.9-39.1)`."""
    if value is None or not episodes:
        return _pct(value)
    low, high = wilson_interval(round(value * episodes / 100.0), episodes)
    return format_interval(value, (100.0 * low, 100.0 * high))


def _fraction(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def markdown_table(runs: list[RunFigures]) -> str:
    """One row per run: steps, offline figures, SR per split, more cities, all unseen, openfly SR, behaviour, and
    (runs of `read_runs`) the paired SR difference from the reference run.

    Every SR carries its Wilson 95 % interval; "SR all unseen" pools the successes of the main and the more cities'
    test_unseen episodes and says how many of how many succeeded."""
    more_names = sorted({name for run in runs for name in run.more_cities})
    reference = next((row["reference"] for run in runs for row in run.vs_reference.values()), None)
    header = ["run", "nav. steps", "offline acc. / IoU (evaluated agent)", "SR seen / unseen (standard)"]
    header += [f"SR {name}" for name in more_names]
    header += ["SR all unseen", "`openfly` seen / unseen", "collisions unseen", "stopped unseen"]
    if reference is not None:
        header.append(f"SR - {reference}, seen / unseen (pp, 95 % CI, McNemar p)")
    lines = ["| " + " | ".join(header) + " |", "|---|" + "---:|" * (len(header) - 1)]
    for run in runs:
        seen, unseen = C.SPLIT_TEST_SEEN, C.SPLIT_TEST_UNSEEN
        more = [_rate(*run.more_cities[n]) if n in run.more_cities else "-" for n in more_names]
        all_unseen = "-"
        if run.all_unseen_episodes:
            successes = round(run.all_unseen_sr * run.all_unseen_episodes / 100.0)
            all_unseen = f"{_rate(run.all_unseen_sr, run.all_unseen_episodes)}, {successes} of {run.all_unseen_episodes}"
        n_seen, n_unseen = run.episodes.get(seen), run.episodes.get(unseen)
        cells = [
            run.name,
            f"{run.navigation_steps:,}",
            f"{_fraction(run.offline_accuracy)} / {_fraction(run.offline_box_iou)}",
            f"{_rate(run.sr.get(seen), n_seen)} / {_rate(run.sr.get(unseen), n_unseen)}",
            *more,
            all_unseen,
            f"{_rate(run.sr_openfly.get(seen), n_seen)} / {_rate(run.sr_openfly.get(unseen), n_unseen)}",
            f"{_pct(run.collisions_unseen)} %",
            f"{_pct(run.stopped_unseen)} %",
        ]
        if reference is not None:
            cells.append(
                f"{_paired(run, seen)} / {_paired(run, unseen)}" if run.vs_reference else "(reference)"
            )
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
