"""Paired comparison of two evaluated policies: the statistics on hand-computed cases, and the command."""

from __future__ import annotations

import json
import sys
from fractions import Fraction
from pathlib import Path

import pytest
from eval_helpers import policy_folder, success_record

from openfly_agent.eval.paired_stats import (
    PairedCounts,
    mcnemar_exact_p,
    newcombe_paired_interval,
    paired_bootstrap_interval,
)
from openfly_agent.rollout.stats import wilson_interval
from openfly_agent.utils.processes import run_group

REPO = Path(__file__).resolve().parents[2]


def _binomial_tail(k: int, n: int) -> Fraction:
    """P(X <= k), X ~ Bin(n, 1/2), by the ratio pmf(i + 1) / pmf(i) = (n - i) / (i + 1) (no math.comb)."""
    pmf, total = Fraction(1, 2**n), Fraction(0)
    for i in range(k + 1):
        total += pmf
        pmf = pmf * (n - i) / (i + 1)
    return total


def test_mcnemar_exact_p_on_hand_checked_cases():
    # 65 vs 37 discordant episodes (the p = 0.007): 2 P(X <= 37), X ~ Bin(102, 1/2) = 0.00721; the normal
    # approximation with continuity correction agrees: z = (28 - 1) / sqrt(102) = 2.673, two-sided 0.0075
    assert mcnemar_exact_p(65, 37) == pytest.approx(float(2 * _binomial_tail(37, 102)), rel=1e-12)
    assert round(mcnemar_exact_p(65, 37), 4) == 0.0072
    assert mcnemar_exact_p(37, 65) == mcnemar_exact_p(65, 37)
    assert mcnemar_exact_p(0, 0) == 1.0  # no discordant pair: no evidence
    assert mcnemar_exact_p(3, 1) == 0.625  # 2 (1 + 4) / 16
    assert mcnemar_exact_p(2, 2) == 1.0  # 2 * 11/16 capped at 1
    assert mcnemar_exact_p(6, 0) == 2 / 64


def test_wilson_interval_by_hand():
    # 3 of 4, z^2 = 3.841459: centre (3 + 1.920729) / 7.841459 = 0.627526,
    # half 1.959964 sqrt(0.75 + 0.960365) / 7.841459 = 0.326886
    low, high = wilson_interval(3, 4)
    assert low == pytest.approx(0.300640, abs=2e-6) and high == pytest.approx(0.954412, abs=2e-6)


def test_newcombe_interval_of_a_four_episode_case():
    # A = [1, 1, 0, 0], B = [1, 0, 1, 1]: both 1, only A 1, only B 2, neither 0; p_B = 3/4, p_A = 1/2, d = 1/4.
    # Wilson: 3/4 -> (0.300640, 0.954412), 2/4 -> (0.150040, 0.849960). phi = (1*0 - 2*1) / sqrt(3*1*2*2) = -0.577350.
    # lower = 0.25 - sqrt(0.449360^2 + 2 * 0.577350 * 0.449360 * 0.349960 + 0.349960^2) = 0.25 - 0.711326
    # upper = 0.25 + sqrt(0.204412^2 + 2 * 0.577350 * 0.204412 * 0.349960 + 0.349960^2) = 0.25 + 0.496849
    counts = PairedCounts.of([True, True, False, False], [True, False, True, True])
    assert counts == PairedCounts(both=1, only_a=1, only_b=2, neither=0)
    difference, lower, upper = newcombe_paired_interval(counts)
    assert difference == 0.25
    assert lower == pytest.approx(-0.461326, abs=1e-5) and upper == pytest.approx(0.746849, abs=1e-5)


def test_paired_bootstrap_interval():
    # every episode differs by the same 0.5: every resample's mean is 0.5
    assert paired_bootstrap_interval([0.0, 0.2, 0.4], [0.5, 0.7, 0.9], resamples=50) == pytest.approx(
        (0.5,) * 3
    )
    a, b = [1.0, 1.0, 0.0, 0.0], [1.0, 0.0, 1.0, 1.0]
    mean, lower, upper = paired_bootstrap_interval(a, b, resamples=2000, seed=3)
    assert mean == 0.25 and lower <= 0.25 <= upper
    # a resample's mean of four differences in {-1, 0, 1} is a multiple of 1/4
    assert (lower * 4).is_integer() and (upper * 4).is_integer() and -1 <= lower < upper <= 1
    assert paired_bootstrap_interval(a, b, resamples=2000, seed=3) == (mean, lower, upper)  # seeded


# -- the command ------------------------------------------------------------------------------------------
def _compare(*args: str):
    return run_group([sys.executable, "-m", "openfly_agent.eval.compare", *args], timeout=120, cwd=REPO)


def test_compare_command_pairs_two_runs(tmp_path):
    a = policy_folder(tmp_path / "a", {"e0": True, "e1": True, "e2": False, "e3": False})
    b = policy_folder(
        tmp_path / "b",
        {"e0": True, "e1": False, "e2": True, "e3": True},
        memory_probe="empty",
        checkpoint="c2",
    )
    out = tmp_path / "cmp" / "out.json"
    done = _compare(str(a), str(b), f"--json={out}", "--resamples=500")
    assert done.returncode == 0, done.stderr
    numbers = json.loads(out.read_text())
    assert numbers["a"]["memory_probe"] == "none" and numbers["b"]["memory_probe"] == "empty"
    for profile in ("openfly", "standard"):
        row = numbers["splits"]["test_seen"][profile]
        assert row["counts"] == {"both": 1, "only_a": 1, "only_b": 2, "neither": 0}
        assert (row["sr_a_pct"], row["sr_b_pct"], row["sr_diff_pp"]) == (50.0, 75.0, 25.0)
        # the hand-computed Newcombe interval above, in percentage points
        assert row["sr_diff_ci_pp"] == pytest.approx([-46.1326, 74.6849], abs=1e-3)
        assert row["mcnemar_p"] == 1.0  # b = 1, c = 2: 2 * (1 + 3) / 8 capped at 1
    # standard: SPL = success * L / max(P, L) with P = L = 100 m, so the SPL difference is the SR difference
    assert numbers["splits"]["test_seen"]["standard"]["spl_diff_pp"] == pytest.approx(25.0)
    # the probe is the one thing shown that differs, and the table prints it
    assert "memory_probe empty" in done.stdout and "| test_seen / `standard` | 4 |" in done.stdout
    assert "+25.0 [-46.1, +74.7]" in done.stdout


def test_compare_refuses_other_episodes_in_one_line(tmp_path):
    a = policy_folder(tmp_path / "a", {"e0": True, "e1": True, "e2": False, "e3": False})
    b = policy_folder(tmp_path / "b", {"e0": True, "e1": False, "e2": True, "e9": True})
    done = _compare(str(a), str(b))
    assert done.returncode == 2 and done.stdout == ""
    assert len(done.stderr.strip().splitlines()) == 1
    assert "1 of A's 4 are not in B and 1 of B's 4 are not in A (e.g. test_seen/e3)" in done.stderr


def test_compare_refuses_other_settings_and_other_episode_content(tmp_path):
    a = policy_folder(tmp_path / "a", {"e0": True, "e1": False})
    b = policy_folder(tmp_path / "b", {"e0": True, "e1": False}, max_steps=50)
    done = _compare(str(a), str(b))
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
    assert "max_steps: 100 vs 50" in done.stderr
    c = policy_folder(tmp_path / "c", {"e0": True, "e1": False})
    lines = (c / "episodes.jsonl").read_text().splitlines()
    moved = success_record("e1", False, goal=[90.0, 0.0, 10.0])  # the same id, another goal: another dataset
    (c / "episodes.jsonl").write_text("\n".join([lines[0], moved.to_json()]) + "\n")
    done = _compare(str(a), str(c))
    assert done.returncode == 2 and "episode test_seen/e1 has another goal" in done.stderr
    done = _compare(str(a), str(tmp_path))  # not a policy folder
    assert done.returncode == 2 and "no run_identity.json" in done.stderr


def test_compare_help_and_bad_option(tmp_path):
    done = _compare("--help")
    assert done.returncode == 0 and "--resamples" in done.stdout and "compare A B" in done.stdout
    a = policy_folder(tmp_path / "a", {"e0": True})
    done = _compare(str(a), str(a), "--resample=3")
    assert done.returncode == 2 and "did you mean --resamples?" in done.stderr


def test_compare_splits_option_reads_only_the_named_splits(tmp_path):
    """A folder that also holds the test splits pairs with a val-only folder on `splits=[val]`, and a split one
    folder lacks is refused in one line."""

    def folder(name, successes, extra=()):
        path = policy_folder(tmp_path / name, {})
        records = [success_record(eid, ok, split="val") for eid, ok in successes.items()] + list(extra)
        (path / "episodes.jsonl").write_text("".join(r.to_json() + "\n" for r in records))
        return path

    a = folder("a", {"e0": True, "e1": False})
    b = folder("b", {"e0": True, "e1": True}, [success_record("t0", True, split="test_seen")])
    out = tmp_path / "out.json"
    assert _compare(str(a), str(b)).returncode == 2  # all splits: B flew an episode A did not
    done = _compare(str(a), str(b), "--splits=[val]", f"--json={out}", "--resamples=200")
    assert done.returncode == 0, done.stderr
    numbers = json.loads(out.read_text())
    assert list(numbers["splits"]) == ["val"]
    assert numbers["splits"]["val"]["standard"]["counts"] == {
        "both": 1,
        "only_a": 0,
        "only_b": 1,
        "neither": 0,
    }
    done = _compare(str(a), str(b), "--splits=[test_seen]")
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
    assert "holds no episode of split test_seen (it holds val)" in done.stderr
