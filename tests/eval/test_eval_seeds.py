"""One policy over training seeds: the across-seed figures on hand-computed cases, and the command."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from eval_helpers import policy_folder, success_record

from openfly_agent.eval.seeds import paired_over_seeds, seeds_split
from openfly_agent.utils.processes import run_group

REPO = Path(__file__).resolve().parents[2]


def test_seeds_split_by_hand():
    # three seeds on four episodes: 2, 1 and 3 of 4 succeed
    successes = np.array([[1, 1, 0, 0], [1, 0, 0, 0], [1, 1, 1, 0]], dtype=bool)
    row = seeds_split(successes, resamples=2000, seed=1)
    assert row["sr_per_seed_pct"] == [50.0, 25.0, 75.0]
    assert row["successes_per_seed"] == [2, 1, 3]
    assert row["sr_mean_pct"] == pytest.approx(50.0)  # per episode 1, 2/3, 1/3, 0: mean 1/2
    assert row["sr_range_pct"] == [25.0, 75.0]
    assert row["sr_std_pct"] == pytest.approx(25.0)  # sample std of 50, 25, 75
    # Wilson of 3 of 4 (tests/eval/test_eval_compare.py): 30.0640-95.4412
    assert row["sr_per_seed_ci_pct"][2] == pytest.approx([30.0640, 95.4412], abs=1e-3)
    # a resample's mean of four values in {0, 1/3, 2/3, 1} is a multiple of 1/12
    low, high = row["sr_mean_ci_pct"]
    assert 0.0 <= low < 50.0 < high <= 100.0
    assert (low / 100 * 12) == pytest.approx(round(low / 100 * 12)) and (high / 100 * 12) == pytest.approx(
        round(high / 100 * 12)
    )
    assert seeds_split(successes, resamples=2000, seed=1) == row  # seeded
    assert "sr_mean_diff_pp" not in row


def test_seeds_split_against_a_reference():
    successes = np.array([[1, 1, 0, 0], [1, 1, 0, 0]], dtype=bool)
    reference = np.array([1, 0, 0, 0], dtype=bool)
    row = seeds_split(successes, reference, resamples=500)
    assert row["reference_sr_pct"] == 25.0
    assert row["sr_mean_diff_pp"] == pytest.approx(25.0)
    assert row["sr_std_pct"] == 0.0  # two equal seeds
    # per-episode differences 0, 1, 0, 0: every resample's mean is a multiple of 1/4 in [0, 1]
    low, high = row["sr_mean_diff_ci_pp"]
    assert 0.0 <= low <= 25.0 <= high <= 100.0 and (low / 25).is_integer() and (high / 25).is_integer()


def _seeds(*args: str):
    return run_group([sys.executable, "-m", "openfly_agent.eval.seeds", *args], timeout=120, cwd=REPO)


def test_seeds_command_with_a_reference(tmp_path):
    runs = [
        policy_folder(tmp_path / "s7", {"e0": True, "e1": True, "e2": False, "e3": False}, checkpoint="c7"),
        policy_folder(tmp_path / "s8", {"e0": True, "e1": False, "e2": False, "e3": False}, checkpoint="c8"),
        policy_folder(tmp_path / "s9", {"e0": True, "e1": True, "e2": True, "e3": False}, checkpoint="c9"),
    ]
    reference = policy_folder(tmp_path / "ref", {"e0": False, "e1": True, "e2": True, "e3": True})
    out = tmp_path / "seeds.json"
    done = _seeds(*map(str, runs), f"--reference={reference}", f"--json={out}", "--resamples=300")
    assert done.returncode == 0, done.stderr
    numbers = json.loads(out.read_text())
    row = numbers["splits"]["test_seen"]["standard"]
    assert row["sr_per_seed_pct"] == [50.0, 25.0, 75.0] and row["sr_mean_pct"] == pytest.approx(50.0)
    assert row["reference_sr_pct"] == 75.0 and row["sr_mean_diff_pp"] == pytest.approx(-25.0)
    # seed 8 vs the reference: both e0? no (ref fails e0); only ref e1, e2, e3; only seed e0
    assert row["per_seed_vs_reference"][1]["counts"] == {"both": 0, "only_a": 3, "only_b": 1, "neither": 0}
    assert "| test_seen / `standard` | 4 | 50.0 (15.0-85.0), 2 of 4; 25.0 (4.6-69.9), 1 of 4;" in done.stdout
    assert "| 25.0-75.0 / 25.0 | 75.0 | -25.0 [" in done.stdout


def test_seeds_command_refuses_unpaired_runs_and_one_run_in_one_line(tmp_path):
    a = policy_folder(tmp_path / "a", {"e0": True, "e1": False})
    b = policy_folder(tmp_path / "b", {"e0": True, "e9": False})
    done = _seeds(str(a), str(b))
    assert done.returncode == 2 and done.stdout == "" and len(done.stderr.strip().splitlines()) == 1
    assert "flew other episodes" in done.stderr
    done = _seeds(str(a))
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
    assert "at least two policy folders" in done.stderr


def _records(successes: dict[str, bool]) -> list:
    return [success_record(eid, ok, "test_seen") for eid, ok in successes.items()]


def test_paired_over_seeds_by_hand():
    # seed 7: the change wins e1 (+25 pp); seed 8: it loses e0 (-25 pp)
    baselines = [
        _records({"e0": True, "e1": False, "e2": False, "e3": False}),
        _records({"e0": True, "e1": True, "e2": False, "e3": False}),
    ]
    runs = [
        _records({"e0": True, "e1": True, "e2": False, "e3": False}),
        _records({"e0": False, "e1": True, "e2": False, "e3": False}),
    ]
    paired = paired_over_seeds(baselines, runs, "standard", resamples=200)
    assert [row["sr_diff_pp"] for row in paired["per_seed"]] == [25.0, -25.0]
    assert paired["per_seed"][0]["counts"] == {"both": 1, "only_a": 0, "only_b": 1, "neither": 2}
    assert paired["seeds_below_zero"] == 1
    pooled = paired["pooled"]  # 8 pairs: both 2 (s7 e0, s8 e1), only A 1, only B 1, neither 4
    assert pooled["episodes"] == 8
    assert pooled["counts"] == {"both": 2, "only_a": 1, "only_b": 1, "neither": 4}
    assert pooled["sr_a_pct"] == 37.5 and pooled["sr_b_pct"] == 37.5 and pooled["sr_diff_pp"] == 0.0
    assert pooled["mcnemar_p"] == 1.0  # one discordant pair each way
    low, high = pooled["sr_diff_ci_pp"]
    assert low < 0.0 < high


def test_seeds_command_paired_with_each_seeds_own_run(tmp_path):
    runs = [
        policy_folder(tmp_path / "s7", {"e0": True, "e1": True, "e2": False, "e3": False}, checkpoint="c7"),
        policy_folder(tmp_path / "s8", {"e0": True, "e1": True, "e2": True, "e3": False}, checkpoint="c8"),
    ]
    own = [
        policy_folder(tmp_path / "b7", {"e0": True, "e1": False, "e2": False, "e3": False}, checkpoint="b7"),
        policy_folder(tmp_path / "b8", {"e0": True, "e1": True, "e2": False, "e3": False}, checkpoint="b8"),
    ]
    out = tmp_path / "paired.json"
    done = _seeds(*map(str, runs), f"--paired_with=[{own[0]},{own[1]}]", f"--json={out}", "--resamples=200")
    assert done.returncode == 0, done.stderr
    paired = json.loads(out.read_text())["splits"]["test_seen"]["standard"]["vs_paired_with"]
    # 8 pairs: A 3 of 8, B 5 of 8; only B 2 (s7 e1, s8 e2), only A 0: exact McNemar p = 2 * (1/2)^2 = 0.5
    assert paired["pooled"]["counts"] == {"both": 3, "only_a": 0, "only_b": 2, "neither": 3}
    assert paired["pooled"]["mcnemar_p"] == pytest.approx(0.5)
    assert paired["seeds_below_zero"] == 0
    assert "| test_seen / `standard` | 8 | 37.5 -> 62.5 | +25.0 [" in done.stdout
    assert "| 0 / 2 | +25.0 [" in done.stdout and "| 0 of 2 |" in done.stdout


def test_seeds_command_refuses_a_paired_with_list_of_another_length(tmp_path):
    runs = [policy_folder(tmp_path / f"s{i}", {"e0": True}) for i in range(2)]
    done = _seeds(*map(str, runs), f"--paired_with=[{runs[0]}]")
    assert (
        done.returncode == 2 and "one per run" in done.stderr and len(done.stderr.strip().splitlines()) == 1
    )
