"""`python -m openfly_agent.eval.compare <eval dir A>/<policy> <eval dir B>/<policy> [--json=out.json]`

Two policies flown on the same episodes, compared pair by pair: per split and metric profile, the SR difference
B - A with its 95 % interval (Newcombe's method 10 for paired proportions) and the exact McNemar p-value of the
discordant episodes, the four counts (both succeed / only A / only B / neither), and the SPL difference with a
paired bootstrap interval (eval/paired_stats.py). Each episode is scored again from its record under the profile
(eval/report.py `episode_rows`), so the numbers come from the two `episodes.jsonl` logs alone.

It refuses, in one line and exit code 2, two folders that did not fly the same episodes under the same settings:
the `run_identity.json` fields of `MATCHED_SETTINGS`, the same (split, episode id) set, and for each episode the
same scene, instruction, goal and reference path. What is compared is allowed to differ (`ALLOWED_TO_DIFFER`:
the policy, its checkpoint and weights, its decoding, the memory probe, a baseline's seed, the dataset's path);
the header prints it. Exit codes: 0 done, 2 bad input. docs/EVAL.md, "Comparing two policies".
"""

from __future__ import annotations

import dataclasses
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from openfly_agent.eval.config import PROFILE_NAMES, EvalInputError
from openfly_agent.eval.distributed import read_all_logs
from openfly_agent.eval.paired_stats import (
    BOOTSTRAP_RESAMPLES,
    BOOTSTRAP_SEED,
    PairedCounts,
    mcnemar_exact_p,
    newcombe_paired_interval,
    paired_bootstrap_interval,
)
from openfly_agent.eval.report import episode_rows
from openfly_agent.eval.run import read_run_identity
from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.utils.cli_help import command_help, wants_help
from openfly_agent.utils.cli_options import UnknownOptionError
from openfly_agent.utils.config import parse_config
from openfly_agent.utils.errors import RecordError, root_cause

PROG = "python -m openfly_agent.eval.compare"
EXIT_BAD_INPUT = 2
# run_identity.json fields that decide what an episode is and how it is flown and scored: they must match
MATCHED_SETTINGS = ("reader", "max_steps", "sim_type", "sim_width", "sim_height", "sim_occupancy")
# what a comparison is about; printed in the header (a missing memory_probe is the default, none)
ALLOWED_TO_DIFFER = (
    "policy",
    "checkpoint",
    "weights",
    "unnorm_key",
    "decode_rule",
    "memory_probe",
    "seed",
    "oracle_mode",
    "box_servo",
    "dataset_root",
)
EPISODE_FIELDS = ("scene_id", "instruction", "goal", "reference_path")  # the same for a paired episode
METHODS = {
    "sr_interval": "Newcombe (1998) method 10: Wilson score limits of each SR combined with the phi correlation",
    "sr_test": "exact McNemar: two-sided binomial test of the discordant episodes at p = 1/2",
    "spl_interval": "paired bootstrap percentile interval over episodes",
}


class PairingError(EvalInputError):
    """Two evaluation folders that cannot be compared episode by episode (other episodes or other settings)."""


@dataclass
class CompareConfig:
    """Compare two evaluated policies on the same episodes; A and B are the first two values of the command line
    (each `<output_dir>/<policy>` of an eval.py run) or `--a` / `--b`."""

    a: str = ""  # the reference: an eval output folder of one policy, e.g. outputs/eval/agent
    b: str = ""  # the policy compared with it (differences are B - A)
    profiles: list[str] = field(default_factory=lambda: list(PROFILE_NAMES))  # metric profiles reported
    # only these splits of both folders (each must hold them), e.g. [val] when a rule reads val and the folders
    # also hold the test splits ([]: every split, the same in both)
    splits: list[str] = field(default_factory=list)
    json: str | None = None  # also write every number to this JSON file
    resamples: int = BOOTSTRAP_RESAMPLES  # paired bootstrap resamples of the SPL difference
    seed: int = BOOTSTRAP_SEED  # the bootstrap's seed (the same seed gives the same interval)

    def __post_init__(self) -> None:
        if not self.a or not self.b:
            raise ValueError(f"name two policy folders: {PROG} <eval dir A>/<policy> <eval dir B>/<policy>")
        for profile in self.profiles:
            if profile not in PROFILE_NAMES:
                raise ValueError(f"profile {profile!r}: choose from {PROFILE_NAMES}")
        if self.resamples < 1:
            raise ValueError(f"resamples={self.resamples} must be >= 1")


@dataclass
class EvaluatedPolicy:
    """One side of a comparison: its folder, `run_identity.json` and scored records."""

    folder: Path
    identity: dict
    records: list[EpisodeRecord]

    @property
    def memory_probe(self) -> str:
        return self.identity.get("memory_probe") or "none"

    def describe(self) -> dict:
        """What is shown of this side: its folder and the fields allowed to differ that it has."""
        identity = {**self.identity, "memory_probe": self.memory_probe}
        shown = {key: identity[key] for key in ALLOWED_TO_DIFFER if key in identity and key != "weights"}
        return {"folder": str(self.folder), **shown}  # (the weights' fingerprint: the checkpoint names them)


def load_policy_folder(folder: str | Path) -> EvaluatedPolicy:
    """A policy folder of an eval.py run, with its records; refuses a folder that is not one, or errored episodes."""
    path = Path(folder)
    identity = read_run_identity(path) if path.is_dir() else None
    if identity is None:
        raise PairingError(
            f"{path}: no run_identity.json: pass the folder of one policy of an eval.py run, "
            "<output_dir>/<policy> (e.g. outputs/eval/agent)"
        )
    records = read_all_logs(path)
    if not records:
        raise PairingError(f"{path}: no episode records (episodes.jsonl is missing or empty)")
    errored = [r for r in records if r.errored]
    if errored:
        raise PairingError(
            f"{path}: {len(errored)} episodes ended in an engine error (e.g. {_name(errored[0].key)}); "
            "run that evaluation again to retry them before comparing"
        )
    return EvaluatedPolicy(path, identity, records)


def only_splits(policy: EvaluatedPolicy, splits: Sequence[str]) -> EvaluatedPolicy:
    """`policy` with the records of `splits` only (all of them when empty); `PairingError` when it lacks one."""
    if not splits:
        return policy
    held = {r.split for r in policy.records}
    missing = [split for split in splits if split not in held]
    if missing:
        raise PairingError(
            f"{policy.folder} holds no episode of split {', '.join(missing)} (it holds {', '.join(sorted(held))})"
        )
    return dataclasses.replace(policy, records=[r for r in policy.records if r.split in splits])


def _name(key: tuple[str, str]) -> str:
    return f"{key[0]}/{key[1]}"


def check_pairing(a: EvaluatedPolicy, b: EvaluatedPolicy) -> None:
    """Raise `PairingError` (one line) unless A and B flew the same episodes under the same settings."""
    changed = [
        f"{key}: {a.identity.get(key)!r} vs {b.identity.get(key)!r}"
        for key in MATCHED_SETTINGS
        if a.identity.get(key) != b.identity.get(key)
    ]
    if changed:
        raise PairingError(
            f"{a.folder} and {b.folder} were flown under other settings ({'; '.join(changed)}): "
            "a paired comparison needs the same ones"
        )
    keys_a, keys_b = {r.key for r in a.records}, {r.key for r in b.records}
    if keys_a != keys_b:
        only_a, only_b = sorted(keys_a - keys_b), sorted(keys_b - keys_a)
        example = _name((only_a or only_b)[0])
        raise PairingError(
            f"{a.folder} and {b.folder} flew other episodes: {len(only_a)} of A's {len(keys_a)} are not in B "
            f"and {len(only_b)} of B's {len(keys_b)} are not in A (e.g. {example}); evaluate both on the same "
            "dataset, splits and max_episodes"
        )
    by_key = {r.key: r for r in b.records}
    for record in a.records:
        other = by_key[record.key]
        for name in EPISODE_FIELDS:
            if getattr(record, name) != getattr(other, name):
                raise PairingError(
                    f"episode {_name(record.key)} has another {name} in {a.folder} than in {b.folder}: "
                    "the two runs read different datasets under the same episode ids"
                )


def paired_records(folder_a: str | Path, folder_b: str | Path, split: str) -> tuple[list, list]:
    """The records of `split` in two policy folders, in pairs (the same episode at each index); none when A has
    no such split; `PairingError` when they did not fly the same episodes under the same settings."""
    a, b = load_policy_folder(folder_a), load_policy_folder(folder_b)
    if split not in {r.split for r in a.records}:
        return [], []
    a, b = only_splits(a, [split]), only_splits(b, [split])
    check_pairing(a, b)
    by_key = {r.key: r for r in b.records}
    return a.records, [by_key[r.key] for r in a.records]


def compare_split(
    records_a: Sequence[EpisodeRecord],
    records_b: Sequence[EpisodeRecord],
    profile: str,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> dict:
    """The paired figures of one split and profile; `records_a[i]` and `records_b[i]` are the same episode."""
    rows_a, rows_b = episode_rows(records_a, profile), episode_rows(records_b, profile)
    counts = PairedCounts.of([r["success"] for r in rows_a], [r["success"] for r in rows_b])
    sr_diff, sr_low, sr_high = newcombe_paired_interval(counts)
    spl_a, spl_b = [r["spl"] for r in rows_a], [r["spl"] for r in rows_b]
    spl_diff, spl_low, spl_high = paired_bootstrap_interval(spl_a, spl_b, resamples, seed)
    n = counts.n
    return {
        "episodes": n,
        "sr_a_pct": 100.0 * (counts.both + counts.only_a) / n,
        "sr_b_pct": 100.0 * (counts.both + counts.only_b) / n,
        "sr_diff_pp": 100.0 * sr_diff,
        "sr_diff_ci_pp": [100.0 * sr_low, 100.0 * sr_high],
        "mcnemar_p": mcnemar_exact_p(counts.only_a, counts.only_b),
        "counts": {
            "both": counts.both,
            "only_a": counts.only_a,
            "only_b": counts.only_b,
            "neither": counts.neither,
        },
        "spl_a_pct": 100.0 * sum(spl_a) / n,
        "spl_b_pct": 100.0 * sum(spl_b) / n,
        "spl_diff_pp": 100.0 * spl_diff,
        "spl_diff_ci_pp": [100.0 * spl_low, 100.0 * spl_high],
    }


def compare_folders(
    folder_a: str | Path,
    folder_b: str | Path,
    profiles: Sequence[str] = PROFILE_NAMES,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
    only: Sequence[str] = (),
) -> dict:
    """Every paired figure of two policy folders, per split and profile (`PairingError` when they do not pair);
    `only`: these splits of both folders (all when empty).

    Shape: {"a": {...}, "b": {...}, "settings": {matched field: value}, "methods": {...}, "resamples", "seed",
    "splits": {split: {profile: `compare_split`}}}.
    """
    a = only_splits(load_policy_folder(folder_a), only)
    b = only_splits(load_policy_folder(folder_b), only)
    check_pairing(a, b)
    by_key = {r.key: r for r in b.records}
    splits: dict[str, dict] = {}
    for split in dict.fromkeys(r.split for r in a.records):
        records_a = [r for r in a.records if r.split == split]
        records_b = [by_key[r.key] for r in records_a]
        splits[split] = {p: compare_split(records_a, records_b, p, resamples, seed) for p in profiles}
    return {
        "a": a.describe(),
        "b": b.describe(),
        "settings": {key: a.identity.get(key) for key in MATCHED_SETTINGS},
        "methods": dict(METHODS),
        "resamples": resamples,
        "seed": seed,
        "splits": splits,
    }


def signed(value: float) -> str:
    return f"{value:+.1f}"


def interval(values: Sequence[float]) -> str:
    return f"[{values[0]:+.1f}, {values[1]:+.1f}]"


def p_value(p: float) -> str:
    return f"{p:.2g}" if p < 0.001 else f"{p:.3f}"


def comparison_markdown(comparison: dict) -> str:
    """The header (what A and B are) and one table row per split and profile."""
    lines = ["## Paired comparison, B - A", ""]
    for side in ("a", "b"):
        described = comparison[side]
        details = ", ".join(f"{k} {v}" for k, v in described.items() if k != "folder" and v is not None)
        lines.append(f"- {side.upper()}: {described['folder']} ({details})")
    lines += [
        "",
        "| split / profile | episodes | SR A / B (%) | SR B - A (pp) [95 % CI] | McNemar p "
        "| both / only A / only B / neither | SPL A / B (%) | SPL B - A (pp) [95 % CI] |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for split, by_profile in comparison["splits"].items():
        for profile, row in by_profile.items():
            counts = row["counts"]
            lines.append(
                f"| {split} / `{profile}` | {row['episodes']} | {row['sr_a_pct']:.1f} / {row['sr_b_pct']:.1f} "
                f"| {signed(row['sr_diff_pp'])} {interval(row['sr_diff_ci_pp'])} | {p_value(row['mcnemar_p'])} "
                f"| {counts['both']} / {counts['only_a']} / {counts['only_b']} / {counts['neither']} "
                f"| {row['spl_a_pct']:.1f} / {row['spl_b_pct']:.1f} "
                f"| {signed(row['spl_diff_pp'])} {interval(row['spl_diff_ci_pp'])} |"
            )
    lines += [
        "",
        f"SR interval: {METHODS['sr_interval']}; p: {METHODS['sr_test']}; SPL interval: "
        f"{METHODS['spl_interval']} ({comparison['resamples']:,} resamples, seed {comparison['seed']}).",
    ]
    return "\n".join(lines) + "\n"


# -- the command ------------------------------------------------------------------------------------------
DESCRIPTION = (
    "Compare two policies evaluated by eval.py on the same episodes (A = the reference, B = the other; "
    "differences are B - A): per split and metric profile, the SR difference with its 95 % interval (Newcombe's "
    "method 10), the exact McNemar p-value, the paired counts, and the SPL difference with a paired bootstrap "
    "interval. Two folders that did not fly the same episodes under the same settings are refused "
    "(docs/EVAL.md, 'Comparing two policies')."
)
EXAMPLES = (
    f"{PROG} outputs/eval/agent outputs/eval-other/agent",
    f"{PROG} outputs/eval/agent outputs/eval-empty-memory/agent --json=outputs/memory_probe.json",
)


def command_args(argv: Sequence[str]) -> list[str]:
    """The command line with its leading values (the two folders) written as `--a=` and `--b=`."""
    args = list(argv)
    leading = []
    while args and not args[0].startswith("-") and len(leading) < 2:
        leading.append(args.pop(0))
    return [f"--{name}={value}" for name, value in zip(("a", "b"), leading)] + args


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (0 done, 2 bad input, one line on stderr)."""
    import draccus  # lazy: --help stays fast

    args = command_args(sys.argv[1:] if argv is None else argv)
    if wants_help(args):
        placeholders = {"a": "<A>", "b": "<B>"}
        sys.stdout.write(
            command_help(CompareConfig, args, f"{PROG} A B", DESCRIPTION, EXAMPLES, placeholders=placeholders)
        )
        return 0
    try:
        cfg = parse_config(CompareConfig, args)
        comparison = compare_folders(cfg.a, cfg.b, cfg.profiles, cfg.resamples, cfg.seed, cfg.splits)
    except (UnknownOptionError, ValueError, RecordError, draccus.utils.ParsingError) as err:
        sys.stderr.write(f"{PROG}: {root_cause(err)}\n")
        return EXIT_BAD_INPUT
    write_report(comparison_markdown(comparison), comparison, cfg.json)
    return 0


def write_report(markdown: str, numbers: dict, json_path: str | None) -> None:
    """The table on stdout, and every number to `json_path` when one is given (the compare commands' output)."""
    sys.stdout.write(markdown)
    if json_path:
        out = Path(json_path)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(numbers, indent=2) + "\n")


if __name__ == "__main__":
    sys.exit(main())
