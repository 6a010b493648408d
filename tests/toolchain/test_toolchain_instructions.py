"""Template instructions: transitions, landmark naming, pronouns, reproducible variety."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from toolchain_scene import synthetic_scene

from openfly_agent.toolchain.config import InstructionConfig
from openfly_agent.toolchain.instructions import (
    InstructionRequest,
    split_at_transitions,
    template_instruction,
)
from openfly_agent.toolchain.instructions.segments import assign_landmarks, image_side, seen_landmark
from openfly_agent.toolchain.instructions.template import PASSED, describe_landmark

# b0 red tower with a spire, b1 blue office building with a billboard, b2 white skyscraper with a dome
LANDMARKS = {lm.landmark_id: lm for lm in synthetic_scene()[1]}


def _request(actions, boxes=None, targets=("b0",), leg_ends=None, seed=0):
    actions = np.array(actions)
    boxes = boxes or [{} for _ in actions]
    stop = int(np.flatnonzero(actions == 0)[0])
    return InstructionRequest(actions, boxes, LANDMARKS, list(targets), list(leg_ends or [stop]), seed=seed)


def test_split_at_transitions():
    segs = split_at_transitions([-1, -1, 3, 3, 9, 9, 1, 2, 4, 4, 0, -2, -2])
    assert [(s.kind, s.start, s.end, s.primitives) for s in segs] == [
        ("takeoff", 0, 2, 2),
        ("right", 2, 4, 2),
        ("forward", 4, 7, 7),  # 9 + 9 + 3 m = 7 steps of 3 m
        ("left", 7, 8, 1),
        ("up", 8, 10, 2),
        ("landing", 11, 13, 2),
    ]
    assert segs[2].metres == 21.0 and segs[1].degrees == 60.0


def test_seen_landmark_is_the_largest_box_above_the_threshold():
    boxes = {
        "a": np.array([0.5, 0.5, 0.1, 0.1]),
        "b": np.array([0.2, 0.5, 0.3, 0.2]),
        "c": np.array([0.9, 0.5, 0.01, 0.01]),
    }
    assert seen_landmark(boxes, 0.002) == "b"
    assert seen_landmark(boxes, 0.002, exclude={"b"}) == "a"
    assert seen_landmark(boxes, 0.5) is None
    assert [image_side(np.array([x, 0.5, 0.1, 0.1])) for x in (0.1, 0.5, 0.9)] == ["left", "center", "right"]


def test_leg_targets_own_the_segment_where_their_leg_ends():
    actions = np.array([9, 9, 2, 2, 9, 1, 0])
    boxes = [{} for _ in actions]
    boxes[2] = {"b2": np.array([0.5, 0.5, 0.2, 0.2])}  # seen at the end of the first forward run
    segs = assign_landmarks(
        _request(actions, boxes, targets=("b1", "b0"), leg_ends=(4, 6)), split_at_transitions(actions)
    )
    assert [(s.kind, s.landmark_id, s.forced) for s in segs] == [
        ("forward", "b2", False),
        ("left", "b1", True),
        ("forward", "b0", True),
    ]


def test_instruction_names_the_target_attributes_and_uses_a_pronoun():
    text = template_instruction(_request([3, 9, 9, 1, 2, 9, 0]))
    red_tower = LANDMARKS["b0"]
    assert text.count("red") == 1 and "tower" in text and "spire" in text  # full name once ...
    assert text.rstrip(".").endswith(" it")  # ... then "it" when stopping at the same landmark
    assert text[0].isupper() and text.endswith(".")
    assert red_tower.color in text and red_tower.feature in text


def test_repeated_landmark_after_another_gets_a_short_name():
    actions = np.array([9, 2, 9, 3, 9, 0])
    boxes = [{} for _ in actions]
    boxes[1] = {"b0": np.array([0.5, 0.5, 0.2, 0.2])}
    boxes[2] = {"b2": np.array([0.5, 0.5, 0.2, 0.2])}
    text = template_instruction(_request(actions, boxes, targets=("b0",)))
    assert "white skyscraper" in text and "dome" in text
    assert text.count("spire") == 1 and "the red tower" in text  # second mention: short name, no feature


def test_phrasing_varies_with_the_seed_and_is_reproducible():
    texts = {template_instruction(_request([3, 9, 9, 1, 2, 9, 0], seed=s)) for s in range(12)}
    assert len(texts) >= 6
    assert template_instruction(_request([3, 9, 0], seed=5)) == template_instruction(
        _request([3, 9, 0], seed=5)
    )


def test_takeoff_turns_climbs_and_landing_are_described():
    text = template_instruction(_request([-1, -1, 2, 2, 2, 2, 2, 2, 4, 4, 9, 0, -2, -2], seed=1)).lower()
    assert any(w in text for w in ("take off", "lift off", "rise from the ground"))
    assert any(w in text for w in ("turn around", "u-turn"))
    assert "6 meters" in text
    assert any(w in text for w in ("land", "touch down", "to the ground"))


def test_describe_landmark_grammar():
    rng = np.random.default_rng(0)
    lm = LANDMARKS["b1"]
    text = describe_landmark(lm, rng)
    assert text.startswith("the ") and "blue office building" in text and "a rooftop billboard" in text
    arched = type(lm)("x", "house", "beige", "low-rise", "rectangular", "arched windows", (0, 0, 0))
    assert "a arched" not in describe_landmark(arched, rng) and "arched windows" in describe_landmark(
        arched, rng
    )
    unnamed = type(lm)("y", "building", "test", "test", "test", "test", (0, 0, 0))
    assert describe_landmark(unnamed, rng) == "the building"


def test_jogs_fold_into_net_turns():
    from openfly_agent.toolchain.instructions.segments import merge_short_segments

    segs = split_at_transitions([9, 9, 2, 1, 3, 9, 9, 3, 8, 3, 9, 0])
    merged = merge_short_segments(segs, 9.0)
    assert [(s.kind, s.start, s.end, s.primitives) for s in merged] == [
        ("forward", 0, 7, 12),  # 18 m + a cancelled left-3 m-right jog + 18 m (the jog's 3 m is dropped)
        ("right", 7, 10, 2),  # right, 6 m, right -> two turns right
        ("forward", 10, 11, 3),
    ]
    assert merge_short_segments(segs, 0.0) == segs  # 0 keeps every transition, as the paper splits
    climbs = split_at_transitions([4, 4, 1, 4, 1, 5, 9, 9, 0])  # up 6, 3 m, up 3, 3 m, down 3, fly on
    assert [(s.kind, s.primitives) for s in merge_short_segments(climbs, 9.0)] == [("up", 2), ("forward", 6)]
    long_jog = split_at_transitions([2, 9, 3, 0])  # a 9 m leg is not a jog
    assert merge_short_segments(long_jog, 9.0) == long_jog


def test_merging_shortens_zigzag_instructions():
    zigzag = [2, 1, 3, 1, 3, 9, 2, 9, 3, 9, 3, 9, 8, 3, 1, 0]
    full = template_instruction(dataclasses.replace(_request(zigzag), merge_short_m=0.0))
    merged = template_instruction(_request(zigzag))
    assert len(merged.split()) < len(full.split())
    assert "red tower" in merged and "spire" in merged


def test_name_every_target_moves_a_target_out_of_a_climb_in_order():
    # forward 6 m, climb 3 m, forward 6 m, STOP; leg 1 (b0, the red tower) ends in the climb (frame 3)
    actions = [9, 9, 4, 9, 9, 0]
    request = _request(actions, targets=("b0", "b1"), leg_ends=(3, 5))
    text = template_instruction(request)
    assert "red" not in text and "blue office building" in text  # the climb's clause names no landmark
    text = template_instruction(dataclasses.replace(request, name_every_target=True))
    assert "red tower" in text and text.index("red tower") < text.index("blue office building")
    segs = assign_landmarks(
        dataclasses.replace(request, name_every_target=True), split_at_transitions(actions)
    )
    assert [(s.kind, s.landmark_id, s.forced) for s in segs] == [
        ("forward", None, False),
        ("up", None, False),
        ("forward", "b0", True),  # b1, whose leg ends here too, is named by the closing stop clause
    ]


def test_name_every_target_keeps_two_targets_of_one_clause_apart():
    request = _request([9, 9, 9, 0], targets=("b0", "b1"), leg_ends=(1, 3))
    assert "red" not in template_instruction(request)  # b1 took the only clause
    text = template_instruction(dataclasses.replace(request, name_every_target=True))
    assert text.index("red tower") < text.index("blue office building")


def test_name_passed_landmark_opens_the_clause_after_a_leg_end_with_the_target_just_reached():
    # forward 18 m to the red tower b0 (leg 1 ends at frame 2), left 90 deg (frames 2-4), forward 18 m, STOP at 7
    actions = [9, 9, 2, 2, 2, 9, 9, 0]
    boxes = [{"b0": np.array([0.5, 0.5, 0.3, 0.3])}] * 3 + [{"b1": np.array([0.5, 0.5, 0.3, 0.3])}] * 5
    request = _request(actions, boxes, targets=("b0", "b1"), leg_ends=(2, 7))
    plain = template_instruction(request)
    assert not any(p in plain for p in PASSED)  # off (the default): no "after passing"
    passed = dataclasses.replace(request, name_passed_landmark=True)
    segs = assign_landmarks(passed, split_at_transitions(actions))
    assert [(s.kind, s.landmark_id, s.passed_id) for s in segs] == [
        ("forward", "b0", None),
        ("left", "b1", "b0"),  # starts at leg 1's end frame: after passing b0, turn to face b1
        ("forward", "b1", None),  # the final target is never "passed"
    ]
    text = template_instruction(passed)
    # b0 was named by the clause just before, so the passed mention is "it"; b1 follows in the same clause
    lead = next(f"{p} it, " for p in PASSED if f"{p} it, " in text)
    assert text.index("red tower") < text.index(lead) < text.index("blue office building")
    assert text.count(lead) == 1


def test_name_passed_landmark_skips_a_clause_that_names_the_target_itself():
    # b0's leg ends in the climb (frame 3); with name_every_target the next forward run names b0 itself, so the
    # "after passing b0" clause is the turn after it, still before leg 2 ends (frame 8)
    actions = [9, 9, 4, 9, 9, 2, 2, 9, 0]
    request = _request(actions, targets=("b0", "b1"), leg_ends=(3, 8))
    request = dataclasses.replace(request, name_every_target=True, name_passed_landmark=True)
    segs = assign_landmarks(request, split_at_transitions(actions))
    assert [(s.kind, s.landmark_id, s.passed_id) for s in segs] == [
        ("forward", None, None),
        ("up", None, None),
        ("forward", "b0", None),
        ("left", None, "b0"),
        ("forward", "b1", None),
    ]
    text = template_instruction(request)
    assert sum(text.count(f"{p} it, ") for p in PASSED) == 1  # b0 was named by the clause just before


def test_name_passed_landmark_is_a_template_option():
    with pytest.raises(ValueError, match="name_passed_landmark is a template option"):
        InstructionConfig(backend="vlm", name_passed_landmark=True)
