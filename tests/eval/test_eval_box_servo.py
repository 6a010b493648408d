"""The reflex reference policy on hand-built boxes."""

from __future__ import annotations

import pytest

from openfly_agent import constants as C
from openfly_agent.eval.box_servo import BoxServoPolicy, BoxServoSettings, servo_action
from openfly_agent.rollout.policy import OBS_TARGET_BOX

S = BoxServoSettings()  # band 0.22, stop 0.45, far 0.15, search 12


@pytest.mark.parametrize(
    ("box", "expected"),
    [
        ((0.20, 0.5, 0.1, 0.1), C.ACTION_TURN_LEFT),  # 0.30 left of centre > 0.22
        ((0.80, 0.5, 0.1, 0.1), C.ACTION_TURN_RIGHT),
        ((0.29, 0.5, 0.1, 0.1), C.ACTION_FORWARD_9),  # 0.21 off: inside the band; area 0.01 < 0.15: far
        ((0.50, 0.5, 0.5, 0.5), C.ACTION_FORWARD),  # area 0.25: between far and stop
        ((0.50, 0.5, 0.7, 0.7), C.ACTION_STOP),  # area 0.49 >= 0.45
        ((0.60, 0.5, 0.9, 0.5), C.ACTION_STOP),  # area 0.45 exactly
        ((0.50, 0.5, 0.3, 0.5), C.ACTION_FORWARD),  # area 0.15 exactly: not far any more
    ],
)
def test_rule_on_hand_built_boxes(box, expected):
    assert servo_action(box, S, steps_unseen=0) == expected


def test_search_turns_left_then_flies_forward():
    assert servo_action(None, S, steps_unseen=0) == C.ACTION_TURN_LEFT
    assert servo_action(None, S, steps_unseen=11) == C.ACTION_TURN_LEFT
    assert servo_action(None, S, steps_unseen=12) == C.ACTION_FORWARD_9


def test_policy_counts_unseen_steps_per_episode_and_resets():
    policy = BoxServoPolicy(BoxServoSettings(search_steps=2))
    a, b = {"episode_id": "a", OBS_TARGET_BOX: None}, {"episode_id": "b", OBS_TARGET_BOX: None}
    seen = {"episode_id": "a", OBS_TARGET_BOX: (0.5, 0.5, 0.1, 0.1)}
    assert policy.act([a, b]) == [C.ACTION_TURN_LEFT, C.ACTION_TURN_LEFT]
    assert policy.act([a]) == [C.ACTION_TURN_LEFT]
    assert policy.act([a, b]) == [C.ACTION_FORWARD_9, C.ACTION_TURN_LEFT]  # a: 2 unseen steps, b: 1
    assert policy.act([seen]) == [C.ACTION_FORWARD_9]  # seeing the target resets the search
    assert policy.act([a]) == [C.ACTION_TURN_LEFT]
    policy.reset(["b"])
    assert policy.act([b]) == [C.ACTION_TURN_LEFT]


def test_policy_refuses_observations_without_the_target_box():
    with pytest.raises(KeyError, match="embedded simulator"):
        BoxServoPolicy().act([{"episode_id": "a"}])


@pytest.mark.parametrize(
    "kwargs",
    [{"center_band": 0.5}, {"far_area": 0.5, "stop_area": 0.4}, {"far_area": 0.0}, {"search_steps": -1}],
)
def test_settings_are_checked(kwargs):
    with pytest.raises(ValueError):
        BoxServoSettings(**kwargs)


def test_box_servo_runs_on_the_true_target_boxes_through_eval(tmp_path):
    """Through the runner, the policy sees the simulator's box of the episode's target landmark each step."""
    from eval_helpers import generate_tiny_dataset

    from openfly_agent.data.openfly_reader import load_openfly_dataset
    from openfly_agent.eval.config import EvalConfig
    from openfly_agent.eval.run import run
    from openfly_agent.rollout.runner import LockstepRunner

    dataset = tmp_path / "data"
    generate_tiny_dataset(dataset)
    seen: list = []
    real = LockstepRunner._observation

    def spy(runner, running):
        obs = real(runner, running)
        seen.append(
            (running.obs.boxes or {}, running.episode.landmark_ids[-1], obs.get(OBS_TARGET_BOX, "absent"))
        )
        return obs

    cfg = EvalConfig(
        policy="box_servo", dataset_root=str(dataset), output_dir=str(tmp_path / "out"), progress=False, plots=0,
        batch_size=2, split=[C.SPLIT_TEST_UNSEEN],
    )  # fmt: skip
    LockstepRunner._observation = spy
    try:
        outcome = run(cfg)
    finally:
        LockstepRunner._observation = real
    episodes = load_openfly_dataset(dataset, C.SPLIT_TEST_UNSEEN)
    standard = outcome["results"]["box_servo"]["splits"][C.SPLIT_TEST_UNSEEN]["standard"]["overall"]
    assert standard["episodes"] == len(episodes)
    assert seen and all(box != "absent" for _, _, box in seen)
    for boxes, target, box in seen:
        expected = boxes.get(target)
        assert (box is None) == (expected is None)
        if box is not None:
            assert box == pytest.approx(list(expected))


def test_box_servo_needs_the_embedded_simulator():
    from openfly_agent.eval.config import EvalConfig, UnrealCVSimSettings

    with pytest.raises(ValueError, match="embedded simulator"):
        EvalConfig(policy="random", baselines=["box_servo"], sim=UnrealCVSimSettings())
