"""`python -m openfly_agent.eval.seeds <seed 1 dir>/<policy> <seed 2 dir>/<policy> ... [--reference=<dir>/<policy>]`

One policy trained under several training seeds, each run evaluated on the same episodes: per split and metric
profile, each seed's SR with its Wilson interval, the mean over the seeds with a 95 % interval, the spread across
the seeds (range and standard deviation), and, given a reference policy flown on the same episodes (e.g. the
`box_servo` baseline), the mean paired SR difference with its interval and each seed's own paired comparison
(eval/compare.py). With `--paired_with` (the same seeds trained without a change, one folder per run, in the same
order) each run is compared with its own seed's run, and all the pairs are pooled: the question "does the change
help, over these seeds?" on the same episodes.

The interval of the mean is a percentile bootstrap over the episodes of each episode's success averaged over the
seeds (the episodes are resampled; the seeds stay): it is what the evaluation set leaves uncertain about these
seeds' mean. The seeds' own variation is not in it; the range and standard deviation beside it show that, and with
three seeds they are the honest statement of it. The pooled comparison with `--paired_with` counts every (seed,
episode) as one pair (S x N pairs): Newcombe's interval and the exact McNemar p of `eval.compare` on them. An
episode flown under three seeds is three pairs; the seeds are independent trainings, but an episode that is hard
for every seed makes its pairs alike, so read the pooled interval together with each seed's own. Each folder must
pair with the first (the same episodes under the same settings, `compare.check_pairing`), else one line and exit
code 2. docs/EVAL.md, "Across training seeds".
"""

from __future__ import annotations

import statistics
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from openfly_agent.eval.compare import (
    EXIT_BAD_INPUT,
    EvaluatedPolicy,
    check_pairing,
    compare_split,
    interval,
    load_policy_folder,
    signed,
    write_report,
)
from openfly_agent.eval.config import PROFILE_NAMES
from openfly_agent.eval.paired_stats import BOOTSTRAP_RESAMPLES, BOOTSTRAP_SEED
from openfly_agent.eval.report import episode_rows
from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.rollout.stats import bootstrap_mean_interval, format_interval, wilson_interval
from openfly_agent.utils.cli_help import command_help, wants_help
from openfly_agent.utils.cli_options import UnknownOptionError
from openfly_agent.utils.config import parse_config
from openfly_agent.utils.errors import RecordError, root_cause

PROG = "python -m openfly_agent.eval.seeds"
METHOD = (
    "mean over the seeds; its 95 % interval: percentile bootstrap over the episodes of each episode's success "
    "averaged over the seeds (evaluation-set uncertainty for these seeds; the spread across seeds is the range)"
)


@dataclass
class SeedsConfig:
    """One policy's evaluations under several training seeds; the folders are the leading values of the command
    line (each `<output_dir>/<policy>` of an eval.py run) or `--runs=[...]`."""

    runs: list[str] = field(default_factory=list)  # one eval policy folder per training seed (at least 2)
    reference: str | None = None  # a policy flown on the same episodes to compare with, e.g. <dir>/box_servo
    # the same seeds without the change, one folder per run in the same order: each run is compared with its own
    # seed's folder (B = the run, A = its folder here), and the pairs of all seeds are pooled
    paired_with: list[str] = field(default_factory=list)
    profiles: list[str] = field(default_factory=lambda: list(PROFILE_NAMES))  # metric profiles reported
    json: str | None = None  # also write every number to this JSON file
    resamples: int = BOOTSTRAP_RESAMPLES  # bootstrap resamples over the episodes
    seed: int = BOOTSTRAP_SEED  # the bootstrap's seed (the same seed gives the same interval)

    def __post_init__(self) -> None:
        if len(self.runs) < 2:
            raise ValueError(
                f"name at least two policy folders, one per training seed: {PROG} <dir seed A>/<policy> "
                f"<dir seed B>/<policy> ... (got {len(self.runs)})"
            )
        if self.paired_with and len(self.paired_with) != len(self.runs):
            raise ValueError(
                f"--paired_with names {len(self.paired_with)} folders for {len(self.runs)} runs: give one per run, "
                "in the same order (each seed's run without the change)"
            )
        for profile in self.profiles:
            if profile not in PROFILE_NAMES:
                raise ValueError(f"profile {profile!r}: choose from {PROFILE_NAMES}")
        if self.resamples < 1:
            raise ValueError(f"resamples={self.resamples} must be >= 1")


def seeds_split(
    successes: np.ndarray,
    reference: np.ndarray | None = None,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> dict:
    """The across-seed figures of one split and profile.

    Args:
        successes: (S, N) booleans, seed s's success on episode n (the same episode order in every row).
        reference: (N,) booleans of a reference policy on the same episodes, or None.
    """
    runs, n = successes.shape
    counts = successes.sum(axis=1)  # (S,)
    per_seed = [100.0 * k / n for k in counts]
    per_episode = successes.mean(axis=0)  # (N,) each episode's success averaged over the seeds
    low, high = bootstrap_mean_interval(per_episode, resamples, seed)
    row = {
        "episodes": n,
        "seeds": runs,
        "sr_per_seed_pct": per_seed,
        "successes_per_seed": [int(k) for k in counts],
        "sr_per_seed_ci_pct": [[100.0 * x for x in wilson_interval(int(k), n)] for k in counts],
        "sr_mean_pct": 100.0 * float(per_episode.mean()),
        "sr_mean_ci_pct": [100.0 * low, 100.0 * high],
        "sr_range_pct": [min(per_seed), max(per_seed)],
        "sr_std_pct": statistics.stdev(per_seed),
    }
    if reference is not None:
        diffs = per_episode - reference.astype(np.float64)  # (N,) paired on the episode
        d_low, d_high = bootstrap_mean_interval(diffs, resamples, seed)
        row["reference_sr_pct"] = 100.0 * float(reference.mean())
        row["sr_mean_diff_pp"] = 100.0 * float(diffs.mean())
        row["sr_mean_diff_ci_pp"] = [100.0 * d_low, 100.0 * d_high]
    return row


def _in_order(policy: EvaluatedPolicy, keys: Sequence[tuple[str, str]]) -> list:
    by_key = {r.key: r for r in policy.records}
    return [by_key[k] for k in keys]


def _successes(policy: EvaluatedPolicy, keys: Sequence[tuple[str, str]], profile: str) -> np.ndarray:
    rows = episode_rows(_in_order(policy, keys), profile)
    return np.array([row["success"] for row in rows], dtype=bool)  # (N,)


def paired_over_seeds(
    baselines: Sequence[Sequence[EpisodeRecord]],
    runs: Sequence[Sequence[EpisodeRecord]],
    profile: str,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> dict:
    """Each seed's run against its own baseline (`baselines[s][i]` and `runs[s][i]` the same episode), and all the
    (seed, episode) pairs pooled into one `compare.compare_split`.

    Shape: {"pooled": `compare_split` of the S x N pairs, "per_seed": [`compare_split`, ...],
    "seeds_below_zero": how many seeds' SR difference (run - baseline) is below 0}.
    """
    per_seed = [compare_split(a, b, profile, resamples, seed) for a, b in zip(baselines, runs)]
    pooled_a = [record for records in baselines for record in records]
    pooled_b = [record for records in runs for record in records]
    return {
        "pooled": compare_split(pooled_a, pooled_b, profile, resamples, seed),
        "per_seed": per_seed,
        "seeds_below_zero": sum(row["sr_diff_pp"] < 0 for row in per_seed),
    }


def summarize_seeds(
    folders: Sequence[str | Path],
    reference: str | Path | None = None,
    profiles: Sequence[str] = PROFILE_NAMES,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
    paired_with: Sequence[str | Path] = (),
) -> dict:
    """Every across-seed figure of the folders (`compare.PairingError` when one does not pair with the first).

    Shape: {"runs": [...], "reference": {...} | None, "paired_with": [...], "method", "resamples", "seed",
    "splits": {split: {profile: `seeds_split` + "per_seed_vs_reference": [`compare.compare_split`, ...]
    + "vs_paired_with": `paired_over_seeds`}}} (the two comparisons only when asked for).
    """
    runs = [load_policy_folder(folder) for folder in folders]
    ref = load_policy_folder(reference) if reference is not None else None
    own = [
        load_policy_folder(folder) for folder in paired_with
    ]  # one per run, the same seed without the change
    for other in runs[1:] + ([ref] if ref is not None else []) + own:
        check_pairing(runs[0], other)
    splits: dict[str, dict] = {}
    for split in dict.fromkeys(r.split for r in runs[0].records):
        keys = [r.key for r in runs[0].records if r.split == split]
        splits[split] = {}
        for profile in profiles:
            successes = np.stack([_successes(run, keys, profile) for run in runs])  # (S, N)
            ref_successes = _successes(ref, keys, profile) if ref is not None else None
            row = seeds_split(successes, ref_successes, resamples, seed)
            if ref is not None:
                ref_records = _in_order(ref, keys)
                row["per_seed_vs_reference"] = [
                    compare_split(ref_records, _in_order(run, keys), profile, resamples, seed) for run in runs
                ]
            if own:
                row["vs_paired_with"] = paired_over_seeds(
                    [_in_order(base, keys) for base in own],
                    [_in_order(run, keys) for run in runs],
                    profile,
                    resamples,
                    seed,
                )
            splits[split][profile] = row
    return {
        "runs": [run.describe() for run in runs],
        "reference": ref.describe() if ref is not None else None,
        "paired_with": [base.describe() for base in own],
        "method": METHOD,
        "resamples": resamples,
        "seed": seed,
        "splits": splits,
    }


def _paired_diff(row: dict) -> str:
    """A `compare.compare_split` row's SR difference, interval and McNemar p: `-25.0 [-60.2, +15.1], p 0.62`."""
    return f"{signed(row['sr_diff_pp'])} {interval(row['sr_diff_ci_pp'])}, p {row['mcnemar_p']:.2g}"


def seeds_markdown(summary: dict) -> str:
    """One row per split and profile: the seeds' SRs, their mean with its interval, the spread, and the reference."""
    lines = ["## Across training seeds", ""]
    for index, run in enumerate(summary["runs"], start=1):
        lines.append(f"- seed run {index}: {run['folder']}")
    reference = summary["reference"]
    if reference is not None:
        lines.append(f"- reference: {reference['folder']}")
    header = "| split / profile | episodes | SR per seed (%) [95 % CI] | SR mean [95 % CI] | range / std |"
    rule = "|---|---:|---|---:|---:|"
    if reference is not None:
        header += (
            " reference SR | mean - reference (pp) [95 % CI] | each seed - reference (pp) [95 % CI], p |"
        )
        rule += "---:|---:|---|"
    lines += ["", header, rule]
    for split, by_profile in summary["splits"].items():
        for profile, row in by_profile.items():
            seeds = "; ".join(
                f"{format_interval(sr, ci)}, {k} of {row['episodes']}"
                for sr, ci, k in zip(
                    row["sr_per_seed_pct"], row["sr_per_seed_ci_pct"], row["successes_per_seed"]
                )
            )
            low, high = row["sr_range_pct"]
            line = (
                f"| {split} / `{profile}` | {row['episodes']} | {seeds} "
                f"| {format_interval(row['sr_mean_pct'], row['sr_mean_ci_pct'])} "
                f"| {low:.1f}-{high:.1f} / {row['sr_std_pct']:.1f} |"
            )
            if reference is not None:
                each = "; ".join(_paired_diff(c) for c in row["per_seed_vs_reference"])
                line += (
                    f" {row['reference_sr_pct']:.1f} | {signed(row['sr_mean_diff_pp'])} "
                    f"{interval(row['sr_mean_diff_ci_pp'])} | {each} |"
                )
            lines.append(line)
    lines += [
        "",
        f"Per seed: Wilson interval. Mean: {summary['method']} ({summary['resamples']:,} resamples, seed "
        f"{summary['seed']}). Each seed - reference: Newcombe method 10 and exact McNemar (eval/compare.py).",
    ]
    if summary["paired_with"]:
        lines += ["", *paired_with_markdown(summary)]
    return "\n".join(lines) + "\n"


def paired_with_markdown(summary: dict) -> list[str]:
    """The section of `--paired_with`: per split and profile, the pooled pairs and each seed's own comparison."""
    lines = [
        "## Each seed against its own run without the change (B = the runs above, A = --paired_with)",
        "",
    ]
    for index, base in enumerate(summary["paired_with"], start=1):
        lines.append(f"- seed run {index} without the change: {base['folder']}")
    lines += [
        "",
        "| split / profile | pairs | SR A -> B, pooled (%) | pooled B - A (pp) [95 % CI], p | only A / only B "
        "| each seed B - A (pp) [95 % CI], p | seeds below 0 |",
        "|---|---:|---:|---:|---:|---|---:|",
    ]
    for split, by_profile in summary["splits"].items():
        for profile, row in by_profile.items():
            paired = row["vs_paired_with"]
            pooled = paired["pooled"]
            each = "; ".join(_paired_diff(seed_row) for seed_row in paired["per_seed"])
            lines.append(
                f"| {split} / `{profile}` | {pooled['episodes']} | {pooled['sr_a_pct']:.1f} -> {pooled['sr_b_pct']:.1f} "
                f"| {_paired_diff(pooled)} | {pooled['counts']['only_a']} / {pooled['counts']['only_b']} | {each} "
                f"| {paired['seeds_below_zero']} of {len(paired['per_seed'])} |"
            )
    lines += [
        "",
        "Pooled: every (seed, episode) is one pair; Newcombe method 10 and exact McNemar (eval/compare.py).",
    ]
    return lines


# -- the command ------------------------------------------------------------------------------------------
DESCRIPTION = (
    "Summarize one policy trained under several training seeds and evaluated on the same episodes: each seed's SR "
    "with its Wilson interval, the mean over the seeds with a bootstrap interval over the episodes, the spread "
    "across the seeds, with --reference a paired comparison against a policy flown on the same episodes, "
    "and with --paired_with each run against its own seed's run without a change, the pairs pooled "
    "(docs/EVAL.md, 'Across training seeds')."
)
EXAMPLES = (
    f"{PROG} outputs/main_job-seed7/eval/agent outputs/main_job-seed8/eval/agent outputs/main_job-seed9/eval/agent",
    f"{PROG} outputs/main_job-seed7/eval/agent outputs/main_job-seed8/eval/agent "
    "--reference=outputs/main_job-seed7/eval/box_servo --json=outputs/seeds.json",
    f"{PROG} outputs/arm-seed7/eval/agent outputs/arm-seed8/eval/agent "
    "--paired_with=[outputs/main_job-seed7/eval/agent,outputs/main_job-seed8/eval/agent] --profiles=[standard]",
)


def command_args(argv: Sequence[str]) -> list[str]:
    """The command line with its leading values (the folders) written as one `--runs=[...]`."""
    args = list(argv)
    leading = []
    while args and not args[0].startswith("-"):
        leading.append(args.pop(0))
    return ([f"--runs=[{','.join(leading)}]"] if leading else []) + args


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (0 done, 2 bad input, one line on stderr)."""
    import draccus  # lazy: --help stays fast

    args = command_args(sys.argv[1:] if argv is None else argv)
    if wants_help(args):
        sys.stdout.write(
            command_help(
                SeedsConfig,
                args,
                f"{PROG} RUN RUN [RUN ...]",
                DESCRIPTION,
                EXAMPLES,
                placeholders={"runs": "<RUN ...>"},
            )
        )
        return 0
    try:
        cfg = parse_config(SeedsConfig, args)
        summary = summarize_seeds(
            cfg.runs, cfg.reference, cfg.profiles, cfg.resamples, cfg.seed, cfg.paired_with
        )
    except (UnknownOptionError, ValueError, RecordError, draccus.utils.ParsingError) as err:
        sys.stderr.write(f"{PROG}: {root_cause(err)}\n")
        return EXIT_BAD_INPUT
    write_report(seeds_markdown(summary), summary, cfg.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
