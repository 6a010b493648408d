"""How an agent turns (bench/analysis/flight_turns.py): hand-counted flights, then the command on a policy folder."""

from __future__ import annotations

import json
import sys

from eval_helpers import oracle_flights

from bench.analysis.flight_turns import TurnCounts
from openfly_agent import constants as C
from openfly_agent.constants import ACTION_FORWARD, ACTION_STOP, ACTION_TURN_LEFT, ACTION_TURN_RIGHT
from openfly_agent.utils.config import REPO_ROOT
from openfly_agent.utils.processes import run_group

L, R, F, S = ACTION_TURN_LEFT, ACTION_TURN_RIGHT, ACTION_FORWARD, ACTION_STOP
CENTRE = [0.5, 0.5, 0.2, 0.2]
NEAR = [0.52, 0.5, 0.2, 0.2]  # IoU with CENTRE 0.82: the same landmark
FAR = [0.1, 0.5, 0.2, 0.2]  # no overlap: another landmark


def test_turns_reversals_and_turn_backs_by_hand():
    counts = TurnCounts()
    # L R: a reversal; R F: a turn kept; F L after a steady box; L L; L S
    counts.add_flight([L, R, F, L, L, S], [CENTRE, NEAR, CENTRE, NEAR, CENTRE, CENTRE])
    summary = counts.summary()
    assert summary["actions"] == 6
    assert summary["turns_per_100"] == round(100 * 4 / 6, 1)  # L R L L
    assert summary["reversals_per_100"] == round(100 * 1 / 6, 1)  # L -> R only
    assert summary["turn_back_percent"] == 25.0  # 4 turns followed by an action, 1 undone
    # straight steps: after F (step 3, L follows, box NEAR vs CENTRE: no switch)
    assert (counts.straight_steps, counts.switches, counts.turns_after_straight) == (1, 0, 1)
    assert summary["head_switch_percent"] == 0.0 and summary["turn_after_switch_percent"] is None


def test_a_switch_while_flying_straight_and_the_turn_after_it():
    counts = TurnCounts()
    # F (box moves CENTRE -> FAR: a switch) then L; F (FAR -> FAR: none) then F; F (box lost: not counted) then S
    counts.add_flight([F, L, F, F, F, S], [CENTRE, FAR, FAR, FAR, None, None])
    summary = counts.summary()
    # straight steps: step 1 (after F, CENTRE -> FAR), step 3 (after F, FAR -> FAR), step 4 (after F, FAR -> None: skipped)
    assert (counts.straight_steps, counts.switches) == (2, 1)
    assert summary["head_switch_percent"] == 50.0
    assert summary["turn_after_switch_percent"] == 100.0  # L after the switch
    assert summary["turn_after_no_switch_percent"] == 0.0  # F after the steady box
    assert summary["turn_back_percent"] == 0.0  # L then F


def test_no_flights_give_no_rates():
    summary = TurnCounts().summary()
    assert (
        summary["actions"] == 0 and summary["turns_per_100"] is None and summary["turn_back_percent"] is None
    )


def test_the_command_reads_a_policy_folder(tmp_path):
    """The oracle's flights (the expert's actions replayed) never undo a turn."""
    split = C.SPLIT_TEST_UNSEEN
    _, folder = oracle_flights(tmp_path, split)
    command = [sys.executable, str(REPO_ROOT / "bench" / "flight_turns.py"), str(folder), f"--split={split}"]
    done = run_group(command, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    row = json.loads(done.stdout.splitlines()[0])
    assert row["split"] == split and row["actions"] > 0 and row["turns_per_100"] > 0
    assert row["reversals_per_100"] == 0.0 and row["turn_back_percent"] == 0.0
