"""The recipe runs' table: figures read from hand-built run folders, hand-checked."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from openfly_agent.recipe.report import markdown_table, read_run
from openfly_agent.recipe.run import DONE_MARKER
from openfly_agent.utils.config import REPO_ROOT


def _profile(
    sr: float, episodes: int, errors: int = 0, collisions: float = 0.0, stopped: float = 100.0
) -> dict:
    return {
        "episodes": episodes,
        "sr_pct": sr,
        "collision_rate_pct": collisions,
        "stop_rate_pct": stopped,
        "errors": errors,
    }


def _make_run(root, seen=(50.0, 4), unseen=(50.0, 4), more=(25.0, 4), unseen_errors=0, iou=0.5, head=True):
    """A finished recipe run: navigation metrics, eval/ and one eval-<cities>/ summary.

    iou: the logged test/box_iou (None: not logged); head: what the run's train_config.json says of the grounding head.
    """
    logs = root / "navigation" / "logs"
    logs.mkdir(parents=True)
    config = {"model": {"grounding": {"enabled": head}}}
    (root / "navigation" / "train_config.json").write_text(json.dumps(config))
    test = {"step": 300, "test/action_accuracy": 0.625}
    if iou is not None:
        test["test/box_iou"] = iou
    records = [{"step": 100, "train/loss": 2.0}, {"step": 200, "test/action_accuracy": 0.5}, test]
    records.append({"step": 310, "train/loss": 1.0})
    (logs / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    summary = {
        "agent": {
            "test_seen": {"standard": _profile(*seen), "openfly": _profile(seen[0] + 25.0, seen[1])},
            "test_unseen": {
                "standard": _profile(*unseen, errors=unseen_errors, collisions=25.0, stopped=75.0),
                "openfly": _profile(unseen[0], unseen[1]),
            },
        },
        "random": {"test_seen": {"standard": _profile(0.0, 4)}},
    }
    (root / "eval").mkdir()
    (root / "eval" / "summary.json").write_text(json.dumps(summary))
    (root / "eval" / DONE_MARKER).write_text("{}\n")
    (root / "eval-more").mkdir()
    more_summary = {"agent": {"test_unseen": {"standard": _profile(*more)}}}
    (root / "eval-more" / "summary.json").write_text(json.dumps(more_summary))
    (root / "eval-more" / DONE_MARKER).write_text("{}\n")  # the recipe finished this evaluation
    return root


def test_a_runs_figures_come_from_its_files(tmp_path):
    run = read_run(_make_run(tmp_path / "arm"))
    assert run.name == "arm" and run.navigation_steps == 310
    assert (run.offline_accuracy, run.offline_box_iou) == (0.625, 0.5)  # the last test evaluation
    assert run.sr == {"test_seen": 50.0, "test_unseen": 50.0}
    assert run.sr_openfly == {"test_seen": 75.0, "test_unseen": 50.0}
    assert (run.collisions_unseen, run.stopped_unseen) == (25.0, 75.0)
    assert run.more_cities == {"more": (25.0, 4)}
    # 2 of 4 main test_unseen episodes + 1 of 4 more: 3 of 8
    assert run.all_unseen_sr == pytest.approx(37.5) and run.all_unseen_episodes == 8


def test_an_evaluation_the_recipe_did_not_finish_is_not_counted(tmp_path):
    root = _make_run(tmp_path / "arm")
    by_hand = root / "eval-r1-unseen-more"  # e.g. an earlier round's agent, evaluated by hand into the run
    by_hand.mkdir()
    by_hand_summary = {"agent": {"test_unseen": {"standard": _profile(100.0, 4)}}}
    (by_hand / "summary.json").write_text(json.dumps(by_hand_summary))
    run = read_run(root)
    assert run.more_cities == {"more": (25.0, 4)}
    assert run.all_unseen_sr == pytest.approx(37.5) and run.all_unseen_episodes == 8


def test_after_dagger_rounds_the_offline_figures_are_the_last_rounds(tmp_path):
    root = _make_run(tmp_path / "dagger")
    # r10 is the last round, though "r10" < "r2" as text; r11 was trained by hand (no marker) and is not the recipe's
    for k, accuracy in ((2, 0.75), (10, 0.875), (11, 0.125)):
        logs = root / "dagger" / f"r{k}" / "train" / "logs"
        logs.mkdir(parents=True)
        record = {"step": 50, "test/action_accuracy": accuracy, "test/box_iou": 0.25}
        (logs / "metrics.jsonl").write_text(json.dumps(record) + "\n")
        if k != 11:
            (logs.parent / DONE_MARKER).write_text("{}\n")
    run = read_run(root)
    assert run.final_stage == "dagger/r10/train" and run.navigation_steps == 310
    assert (run.offline_accuracy, run.offline_box_iou) == (0.875, 0.25)
    assert read_run(_make_run(tmp_path / "plain")).final_stage == "navigation"


def test_after_an_rl_stage_the_evaluated_agent_is_the_rl_stages(tmp_path):
    root = _make_run(tmp_path / "rl")
    (root / "rl" / "logs").mkdir(parents=True)  # an RL stage still running: not the evaluated agent yet
    assert read_run(root).final_stage == "navigation"
    (root / "rl" / DONE_MARKER).write_text("{}\n")
    # the pre-RL agent's evaluation is not one of the more cities' (not an eval-* folder)
    (root / "eval_before_rl").mkdir()
    (root / "eval_before_rl" / DONE_MARKER).write_text("{}\n")
    run = read_run(root)
    assert run.final_stage == "rl"
    # the RL stage runs no offline test: the offline figures stay those of the agent it started from
    assert (run.offline_accuracy, run.offline_box_iou) == (0.625, 0.5)
    assert run.more_cities == {"more": (25.0, 4)}


def test_the_table_has_one_row_per_run_and_a_dash_where_a_figure_is_missing(tmp_path):
    runs = [
        read_run(_make_run(tmp_path / "a"), "with grounding"),
        read_run(_make_run(tmp_path / "b", iou=None, unseen=(25.0, 4)), "no grounding"),
    ]
    lines = markdown_table(runs).splitlines()
    assert len(lines) == 4 and lines[0].startswith("| run | nav. steps |") and "SR more" in lines[0]
    # Every SR with its Wilson 95 % interval (z^2 = 3.841459). 2 of 4: centre 0.5, half = 1.959964
    # * sqrt(0.0625 + 0.060023) / 1.960365 = 0.349962 -> 15.0 .. 85.0. 1 of 4: centre = 0.730182 / 1.960365
    # = 0.372473, half = 1.959964 * sqrt(0.046875 + 0.060023) / 1.960365 = 0.326886 -> 4.6 .. 69.9.
    # 3 of 8: centre = 0.615091 / 1.480182 = 0.415551, half = 1.959964 * sqrt(0.029297 + 0.015006)
    # / 1.480182 = 0.278708 -> 13.7 .. 69.4. 2 of 8: centre = 0.490091 / 1.480182 = 0.331101, half
    # = 1.959964 * sqrt(0.023438 + 0.015006) / 1.480182 = 0.259623 -> 7.1 .. 59.1.
    assert lines[2].startswith(
        "| with grounding | 310 | 0.625 / 0.500 | 50.0 (15.0-85.0) / 50.0 (15.0-85.0) | 25.0 (4.6-69.9) "
        "| 37.5 (13.7-69.4), 3 of 8 |"
    )
    # no box IoU; (1 + 1) of 8
    assert (
        "| 0.625 / - | 50.0 (15.0-85.0) / 25.0 (4.6-69.9) | 25.0 (4.6-69.9) | 25.0 (7.1-59.1), 2 of 8 |"
        in lines[3]
    )


# NaN as the metrics file writes it; a 0.0 logged by a head-less run before the agent logged NaN
@pytest.mark.parametrize(("iou", "head"), [("nan", True), (0.0, False)])
def test_a_run_without_a_measured_box_iou_has_none(tmp_path, iou, head):
    run = read_run(_make_run(tmp_path / "arm", iou=iou, head=head))
    assert run.offline_accuracy == 0.625 and run.offline_box_iou is None
    assert read_run(_make_run(tmp_path / "kept", iou=0.0, head=True)).offline_box_iou == 0.0  # a real 0 stays


def test_failed_episodes_and_missing_steps_are_refused_with_the_file(tmp_path):
    with pytest.raises(ValueError, match=r"eval/summary.json: 1 of the agent's test_unseen episodes failed"):
        read_run(_make_run(tmp_path / "failed", unseen_errors=1))
    unfinished = _make_run(tmp_path / "unfinished")
    (unfinished / "eval" / DONE_MARKER).unlink()  # killed after writing its summary, before the marker
    with pytest.raises(ValueError, match=r"eval: the recipe has not finished this evaluation"):
        read_run(unfinished)
    (unfinished / "eval" / "summary.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"eval/summary.json: missing"):
        read_run(unfinished)
    corrupt = _make_run(tmp_path / "corrupt")
    with (corrupt / "navigation" / "logs" / "metrics.jsonl").open("a") as f:
        f.write("{not json\n")
    with pytest.raises(ValueError, match=r"metrics.jsonl, line 5: not valid JSON"):
        read_run(corrupt)


def test_the_script_prints_the_table_and_writes_json(tmp_path):
    _make_run(tmp_path / "arm")
    out = tmp_path / "table.json"
    script = str(REPO_ROOT / "bench" / "ablation_table.py")
    done = subprocess.run(
        [sys.executable, script, "--run", f"recipe={tmp_path / 'arm'}", "--json", str(out)],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert "| recipe | 310 |" in done.stdout
    assert json.loads(out.read_text())[0]["all_unseen_sr"] == pytest.approx(37.5)
    failed = subprocess.run(
        [sys.executable, script, "--run", str(tmp_path / "none")], capture_output=True, text=True
    )
    assert failed.returncode != 0 and "ablation_table:" in failed.stderr and "missing" in failed.stderr


def test_every_arm_carries_its_paired_difference_from_the_reference(tmp_path):
    from eval_helpers import policy_folder

    from openfly_agent.recipe.report import read_runs

    reference, arm = _make_run(tmp_path / "ref"), _make_run(tmp_path / "arm")
    # test_seen: the reference succeeds on e0 and e1, the arm on e0, e2 and e3 (both 1, only ref 1, only arm 2)
    policy_folder(reference / "eval", {"e0": True, "e1": True, "e2": False, "e3": False})
    policy_folder(arm / "eval", {"e0": True, "e1": False, "e2": True, "e3": True}, checkpoint="other")
    runs = read_runs([("recipe", reference), ("arm", arm)])
    assert runs[0].vs_reference == {}
    paired = runs[1].vs_reference["test_seen"]
    assert paired["reference"] == "recipe" and paired["sr_diff_pp"] == 25.0
    assert paired["counts"] == {"both": 1, "only_a": 1, "only_b": 2, "neither": 0}
    assert paired["mcnemar_p"] == 1.0  # 2 * P(X <= 1 | 3, 1/2) = 2 * 4/8, capped at 1
    # Newcombe's method 10 for this table, worked by hand in tests/eval/test_eval_compare.py
    assert paired["sr_diff_ci_pp"] == pytest.approx([-46.1326, 74.6849], abs=1e-3)
    lines = markdown_table(runs).splitlines()
    assert lines[0].endswith("| SR - recipe, seen / unseen (pp, 95 % CI, McNemar p) |")
    assert lines[2].endswith("| (reference) |")
    assert lines[3].endswith(
        "| +25.0 [-46.1, +74.7], p 1.000 / - |"
    )  # these logs hold no test_unseen episode
    # an arm flown on other episodes is refused, naming both folders
    other = _make_run(tmp_path / "other")
    policy_folder(other / "eval", {"e0": True, "e7": False})
    with pytest.raises(ValueError, match="flew other episodes"):
        read_runs([("recipe", reference), ("other", other)])
