"""The grounding dataset: unique referring expressions (hand-checked and property-tested) and the generated
dataset against a fresh render (each visible landmark once, boxes equal, descriptions resolve to their own)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_toolchain_generate import small_config

from openfly_agent import constants as C
from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.grounding import read_grounding_frames
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.sim.scene import Landmark
from openfly_agent.toolchain.config import GroundingDataConfig
from openfly_agent.toolchain.expressions import (
    attribute_values,
    describe_uniquely,
    frame_expressions,
    resolves_to,
)
from openfly_agent.toolchain.generate import generate
from openfly_agent.toolchain.grounding import generate_grounding, source_render_settings
from openfly_agent.utils.geometry import Pose


def landmark(lid, color="red", type_="building", size="mid-rise", feature="none") -> Landmark:
    return Landmark(lid, type_, color, size, "rectangular", feature, (0.0, 0.0, 0.0))


def frame(*items):
    """visible mapping from (landmark, cx) pairs; boxes are small squares at height 0.5."""
    return {lm.landmark_id: (lm, np.array([cx, 0.5, 0.1, 0.1])) for lm, cx in items}


RNG = np.random.default_rng(0)


def test_distinct_colours_need_only_colour_and_type():
    visible = frame((landmark("a", "red"), 0.2), (landmark("b", "blue"), 0.6))
    expression = describe_uniquely("a", visible, np.random.default_rng(1))
    assert expression.named["color"] == "red" and expression.named["type"] == "building"
    assert "feature" not in expression.named and expression.relation is None
    assert expression.text.startswith("the ") and "red building" in expression.text


def test_a_shared_colour_and_type_adds_the_feature():
    visible = frame((landmark("a", feature="spire"), 0.2), (landmark("b"), 0.6))
    expression = describe_uniquely("b", visible, np.random.default_rng(1))
    # b has no feature to add, so the two red buildings are told apart by their position
    assert expression.relation == "right" and expression.text.endswith("on the right")
    expression = describe_uniquely("a", visible, np.random.default_rng(1))
    assert expression.named["feature"] == "spire" and expression.relation is None
    assert "spire" in expression.text


def test_the_size_word_tells_a_tall_building_from_a_low_one():
    tall, low = landmark("t", size="high-rise"), landmark("l", size="low-rise")
    expression = describe_uniquely("t", frame((tall, 0.5), (low, 0.1)), np.random.default_rng(3))
    assert expression.named["size"] == "tall" and "tall red building" in expression.text


def test_identical_buildings_are_ordered_from_the_left():
    visible = frame(*[(landmark(f"x{i}"), cx) for i, cx in enumerate([0.9, 0.1, 0.5, 0.3])])
    relations = {e.landmark_id: e.relation for e in frame_expressions(visible, RNG)}
    # by box centre: x1 (0.1), x3 (0.3), x2 (0.5), x0 (0.9)
    assert relations == {"x1": "left", "x3": "2/4", "x2": "3/4", "x0": "right"}
    middle = frame(*[(landmark(f"y{i}"), cx) for i, cx in enumerate([0.1, 0.5, 0.9])])
    expression = describe_uniquely("y1", middle, RNG)
    assert expression.relation == "middle" and expression.text.endswith("in the middle")
    second = describe_uniquely("x3", visible, RNG)
    assert second.text.endswith(", the second from the left")


COLORS, TYPES = ["red", "blue", "gray"], ["building", "tower", "house"]
SIZES, FEATURES = ["low-rise", "mid-rise", "high-rise"], ["none", "spire", "dome"]
landmark_specs = st.lists(
    st.tuples(
        st.sampled_from(COLORS), st.sampled_from(TYPES), st.sampled_from(SIZES), st.sampled_from(FEATURES),
        st.floats(0.0, 1.0),
    ),
    min_size=1,
    max_size=9,
)  # fmt: skip


@settings(max_examples=200, deadline=None)
@given(landmark_specs, st.integers(0, 2**31 - 1))
def test_every_expression_names_its_own_attributes_and_resolves_to_it_alone(specs, seed):
    visible = frame(*[(landmark(f"l{i}", c, t, s, f), cx) for i, (c, t, s, f, cx) in enumerate(specs)])
    expressions = frame_expressions(visible, np.random.default_rng(seed))
    assert sorted(e.landmark_id for e in expressions) == sorted(visible)  # each visible landmark once
    for expression in expressions:
        own = attribute_values(visible[expression.landmark_id][0])
        assert all(own[key] == value for key, value in expression.named.items())
        assert {"color", "type"} <= set(expression.named)
        for value in expression.named.values():
            assert value in expression.text
        assert resolves_to(expression, visible) == [expression.landmark_id]


@pytest.fixture(scope="module")
def grounding_root(tmp_path_factory):
    source = tmp_path_factory.mktemp("nav") / "small"
    generate(small_config(source), progress=False)
    out = tmp_path_factory.mktemp("grounding") / "g"
    cfg = GroundingDataConfig(source_root=str(source), output_dir=str(out), yaw_copies=1, frames_per_part=16)
    info = generate_grounding(cfg, progress=False)
    return source, out, cfg, info


def test_generated_frames_match_a_fresh_render(grounding_root):
    from openfly_agent.sim.embedded import EmbeddedSimConfig, EmbeddedSimulator

    source, out, cfg, info = grounding_root
    frames = read_grounding_frames(out)
    assert frames and info["splits"][C.SPLIT_TRAIN]["frames"] == len(frames)
    assert {f.split for f in frames} == {C.SPLIT_TRAIN}  # the alignment data never sees a test city
    width, height, city_cfg = source_render_settings(source)
    with EmbeddedSimulator(EmbeddedSimConfig(width=width, height=height, city=city_cfg)) as sim:
        for f in frames[:: max(1, len(frames) // 12)]:
            obs = sim.render(f.scene_id, Pose(*f.pose), f.pitch_deg)
            expected = {k: b for k, b in obs.boxes.items() if b[2] * b[3] >= cfg.min_box_area}
            assert sorted(f.landmark_ids) == sorted(expected)  # each visible landmark once
            assert len(set(f.landmark_ids)) == len(f.landmark_ids)
            for lid, box in zip(f.landmark_ids, f.boxes):
                np.testing.assert_allclose(box, expected[lid], atol=1e-6)
            # a batched render may differ from a single one by a few pixel values at edges (rasteriser order)
            assert np.abs(f.rgb().astype(int) - obs.rgb.astype(int)).mean() < 0.5
            city = sim.city(f.scene_id)
            visible = {lid: (city.landmark(lid), expected[lid]) for lid in expected}
            for expression in frame_expressions(visible, np.random.default_rng(0)):  # on real frames too
                assert resolves_to(expression, visible) == [expression.landmark_id]
            for lid, text, relation in zip(f.landmark_ids, f.expressions, f.relations):
                own = attribute_values(city.landmark(lid))
                assert own["color"] is None or own["color"] in text
                assert own["type"] in text
                if relation:
                    assert relation in ("left", "right", "middle") or "/" in relation


def test_generation_resumes_scene_by_scene(grounding_root):
    source, out, cfg, info = grounding_root
    parts = sorted((out / "frames").glob("*/*.parquet"))
    mtimes = [p.stat().st_mtime_ns for p in parts]
    assert generate_grounding(cfg, progress=False) == info
    assert [p.stat().st_mtime_ns for p in parts] == mtimes  # nothing re-rendered


def test_poses_come_from_the_source_train_split(grounding_root):
    source, out, _, _ = grounding_root
    train_ids = {e.episode_id for e in load_openfly_dataset(source, C.SPLIT_TRAIN, ReaderOptions())}
    assert {f.source_episode for f in read_grounding_frames(out)} <= train_ids


def test_missing_source_config_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="toolchain"):
        source_render_settings(tmp_path)
