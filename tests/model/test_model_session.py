"""`AgentSession` (model/session.py): batched == one episode at a time, reset, memory updates, cached decoding,
compat mode."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from openfly_agent.model.config import (
    BinsActionHeadConfig,
    CellGroundingConfig,
    DiscreteActionHeadConfig,
    HistoryEncodingConfig,
    KeyframeConfig,
    MemoryConfig,
    PromptConfig,
)
from openfly_agent.model.language.action_tokenizer import CODEBOOK

INSTRUCTIONS = [
    "Fly to the red tower and turn left.",
    "Ascend above the white house, then stop near the blue dome.",
    "Go straight.",
]

NORM_STATS = {"demo": {"action": {"q01": [0.0] * 8, "q99": CODEBOOK.max(axis=0).tolist()}}}


def memory_agent(make_agent, **overrides):
    """An untrained agent whose actions change with the image (seed 1, visual tokens amplified), and where
    every change point yields a keyframe set (all predicted boxes visible, theta = 0)."""
    agent = make_agent(
        seed=1,
        grounding=overrides.pop("grounding", CellGroundingConfig(dim=32, num_heads=2, visibility_weight=0.0)),
        keyframes=KeyframeConfig(theta=0.0),
        **overrides,
    )
    with torch.no_grad():
        agent.network.projector.fc3.weight.mul_(10.0)
    return agent


def _frames(episodes: int, steps: int, size: int = 56, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 256, (episodes, steps, size, size, 3), dtype=np.uint8)
    if steps > 3:
        frames[:, 3] = frames[:, 2]  # a repeated view: its tokens merge into the other one
    return frames


def _obs(episode: int, frame: np.ndarray) -> dict:
    return {
        "episode_id": f"ep{episode}",
        "instruction": INSTRUCTIONS[episode % len(INSTRUCTIONS)],
        "rgb": frame,
        "pose": (0.0, 0.0, 10.0, 0.0),
    }


SKIP_HEAD = CellGroundingConfig(  # cells that get the frame's visual tokens
    dim=32, num_heads=2, visibility_weight=0.0, visual_skip=True
)


COLOUR_HEAD = CellGroundingConfig(  # cells matched by their colour histograms
    dim=32, num_heads=2, visibility_weight=0.0, colour_vocabulary=True
)
HEADS = {
    "plain": {},
    "skip_head": {"grounding": SKIP_HEAD},
    "colour_head": {"grounding": COLOUR_HEAD},
}


@pytest.mark.parametrize("variant", list(HEADS))
def test_batched_equals_one_episode_at_a_time(make_agent, variant):
    agent = memory_agent(make_agent, **HEADS[variant])
    session = agent.new_session()
    episodes, steps = 3, 10
    frames = _frames(episodes, steps, size=agent.model_cfg.vision.image_size)
    batched = [session.predict_step([_obs(e, frames[e, t]) for e in range(episodes)]) for t in range(steps)]
    batched_memory = {e: session.episodes[f"ep{e}"].memory.sets() for e in range(episodes)}
    assert any(batched_memory.values()), "the scripted run should fill some memory"
    session.reset()
    assert session.episodes == {}
    for e in range(episodes):
        for t in range(steps):
            (single,) = session.predict_step([_obs(e, frames[e, t])])
            assert single.action == batched[t][e].action
            torch.testing.assert_close(
                single.action_logits, batched[t][e].action_logits, rtol=1e-4, atol=1e-4
            )
            np.testing.assert_allclose(single.box, batched[t][e].box, rtol=1e-4, atol=1e-5)
        assert session.episodes[f"ep{e}"].memory.sets() == batched_memory[e]


def test_memory_follows_the_keyframe_selector(make_agent):
    agent = memory_agent(make_agent)
    session = agent.new_session()
    frames = _frames(1, 14, seed=3)
    for t in range(14):
        session.select_action([_obs(0, frames[0, t])])
        state = session.episodes["ep0"]
        expected = agent.network.keyframe_selector.select(state.actions, state.box_areas, state.step)
        assert state.memory.sets() == [tuple(s) for s in expected]
        assert len(state.memory.frame_features) <= agent.network.keyframe_selector.set_size + 1
    assert len(session.episodes["ep0"].memory) > 0


def test_black_and_white_images_give_different_action_logits(make_agent):
    agent = make_agent()
    session = agent.new_session()
    size = agent.model_cfg.vision.image_size
    black = np.zeros((size, size, 3), np.uint8)
    white = np.full((size, size, 3), 255, np.uint8)
    results = session.predict_step(
        [{**_obs(0, black), "episode_id": "b"}, {**_obs(0, white), "episode_id": "w"}]
    )
    assert (results[0].action_logits - results[1].action_logits).abs().max() > 1e-3


def test_reset_forgets_one_episode_only(make_agent):
    """After `reset(["ep0"])`, ep1 goes on exactly as in a session that never held ep0; ep0 starts afresh."""
    agent = memory_agent(make_agent)
    frames = _frames(2, 6, seed=2)
    shared, alone = agent.new_session(), agent.new_session()
    for t in range(3):
        shared.predict_step([_obs(0, frames[0, t]), _obs(1, frames[1, t])])
    shared.reset(["ep0"])
    assert set(shared.episodes) == {"ep1"}
    for t in range(3):
        (expected,) = alone.predict_step([_obs(1, frames[1, t])])
    for t in range(3, 6):
        restarted, result = shared.predict_step([_obs(0, frames[0, t - 3]), _obs(1, frames[1, t])])
        (expected,) = alone.predict_step([_obs(1, frames[1, t])])
        assert result.action == expected.action and result.memory_sets == expected.memory_sets
        torch.testing.assert_close(result.action_logits, expected.action_logits, rtol=1e-4, atol=1e-4)
    assert shared.episodes["ep0"].step == 3 and shared.episodes["ep1"].step == 6


def test_sessions_of_one_agent_are_independent(make_agent):
    agent = make_agent()
    frame = _frames(1, 1)[0, 0]
    first, second = agent.new_session(), agent.new_session()
    first.select_action([_obs(0, frame)])
    assert set(first.episodes) == {"ep0"} and second.episodes == {}


def test_reset_and_errors(make_agent):
    agent = make_agent()
    session = agent.new_session()
    frame = _frames(1, 1)[0, 0]
    session.select_action([_obs(0, frame), _obs(1, frame)])
    session.reset(["ep0"])
    assert set(session.episodes) == {"ep1"}
    with pytest.raises(ValueError, match="appears twice"):
        session.select_action([_obs(1, frame), _obs(1, frame)])
    with pytest.raises(ValueError, match="changed its instruction"):
        session.select_action([{**_obs(1, frame), "instruction": "something else"}])
    with pytest.raises(ValueError, match="lacks"):
        session.select_action([{"episode_id": "x", "rgb": frame}])
    assert session.select_action([]) == []


@pytest.mark.parametrize("head", ["discrete", "openvla_bins"])
def test_cached_decoding_uses_the_cache_api_without_deprecation_warnings(make_agent, head):
    """transformers warns (a FutureWarning and a log line, once per process) when `past_key_values` is passed
    or read; select_action's prefill + box token / bins decoding must not."""
    import logging
    import warnings

    from transformers.utils import logging as hf_logging

    head_cfg = BinsActionHeadConfig() if head == "openvla_bins" else DiscreteActionHeadConfig()
    agent = make_agent(action_head=head_cfg, norm_stats=NORM_STATS)
    session = agent.new_session()
    hf_logging.warning_once.cache_clear()  # "once": a warning an earlier test triggered would be silent
    records: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: records.append(record.getMessage())
    hf_logger = hf_logging.get_logger("transformers")
    hf_logger.addHandler(handler)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            frames = _frames(2, 2)
            for t in range(2):
                session.select_action([_obs(e, frames[e, t]) for e in range(2)])
    finally:
        hf_logger.removeHandler(handler)
    messages = [str(w.message) for w in caught] + records
    assert not [m for m in messages if "past_key_values" in m or "deprecated" in m], messages


def test_bins_head_select_action(make_agent):
    agent = make_agent(action_head=BinsActionHeadConfig(decode_rule="nearest"), norm_stats=NORM_STATS)
    session = agent.new_session()
    frames = _frames(2, 3)
    for t in range(3):
        results = session.predict_step([_obs(e, frames[e, t]) for e in range(2)])
        assert all(0 <= r.action <= 9 and r.action_logits.shape == (8,) for r in results)


def test_compat_mode_runs_the_released_layout(make_agent):
    agent = make_agent(
        memory=MemoryConfig(capacity=2, grid=4, encoding=HistoryEncodingConfig()),
        prompt=PromptConfig(template="{instruction}", suffix_token_id=5),
        action_head=BinsActionHeadConfig(),
        norm_stats=NORM_STATS,
    )
    session = agent.new_session()
    frames = _frames(1, 4)
    for t in range(4):
        (result,) = session.predict_step([_obs(0, frames[0, t])])
        assert 0 <= result.action <= 9
    state = session.episodes["ep0"]
    assert state.prompt_ids[-1] == 5 and state.prompt_ids[0] == agent.tokenizer.bos_token_id
    assert sorted(state.memory.tokens) == [0, 2, 3]  # frame 0 (padding) + the last K frames
    # history token = projector(DINO CLS ++ pooled SigLIP patches), one per frame
    pixels = agent.processor.image(frames[0, 3])[None]
    patches, cls = agent.network.vision_backbone.forward_with_cls(pixels)
    manual = agent.network.projector(
        torch.cat([cls, patches[..., agent.network.vision_backbone.dino_dim :].mean(1)], -1)
    )
    torch.testing.assert_close(state.memory.tokens[3], manual[0], rtol=1e-5, atol=1e-5)


def test_true_boxes_replace_the_grounding_heads_prediction(make_agent):
    agent = make_agent(seed=1, keyframes=KeyframeConfig(theta=0.0))  # with a visibility logit
    session = agent.new_session()
    with torch.no_grad():
        agent.network.projector.fc3.weight.mul_(10.0)
    assert agent.network.box_token_embed is not None
    frames = _frames(2, 4, seed=5)
    own = [session.predict_step([_obs(e, frames[e, t]) for e in range(2)]) for t in range(4)]
    session.reset()
    # fed its own predictions as the "true" boxes, the agent acts exactly as before, memory included
    for t in range(4):
        given = [r.box if r.box_visible else None for r in own[t]]
        results = session.predict_step([_obs(e, frames[e, t]) for e in range(2)], true_boxes=given)
        for result, reference in zip(results, own[t]):
            assert result.action == reference.action and result.box_visible == reference.box_visible
            torch.testing.assert_close(result.action_logits, reference.action_logits, rtol=1e-4, atol=1e-4)
    session.reset()
    box = (0.2, 0.7, 0.1, 0.3)
    visible, hidden = session.predict_step(
        [_obs(0, frames[0, 0]), _obs(1, frames[0, 0])], true_boxes=[box, None]
    )
    assert visible.box == pytest.approx(box) and visible.box_visible
    assert not hidden.box_visible and session.episodes["ep1"].box_areas == [None]
    # the same frame and instruction, only the box differs: the box token changes the logits
    session.reset()
    (elsewhere,) = session.predict_step([_obs(0, frames[0, 0])], true_boxes=[(0.8, 0.3, 0.4, 0.2)])
    assert (elsewhere.action_logits - visible.action_logits).abs().max() > 1e-4
    with pytest.raises(ValueError, match="true boxes for"):
        session.predict_step([_obs(0, frames[0, 1])], true_boxes=[box, box])


def _prefill_lengths(agent, session, frames) -> list[list[int]]:
    """Per step, the real (unpadded) positions of each episode's prefill: what the LLM sees at that step."""
    network, seen = agent.network, []
    run_llm = network.run_llm

    def spy(embeds, attention_mask, **kwargs):
        if embeds.shape[1] > 1:  # the prefill (the cached decoding feeds one position at a time)
            seen.append(attention_mask.sum(dim=1).tolist())
        return run_llm(embeds, attention_mask, **kwargs)

    network.run_llm = spy
    try:
        results = [
            session.predict_step([_obs(e, frames[e, t]) for e in range(len(frames))])
            for t in range(frames.shape[1])
        ]
    finally:
        del network.run_llm
    return seen, results


def test_memory_probe_empty_gives_the_llm_no_memory_token(make_agent):
    agent = memory_agent(make_agent)
    frames = _frames(2, 10, size=agent.model_cfg.vision.image_size)
    lengths, _ = _prefill_lengths(agent, agent.new_session(), frames)
    # the model as trained: once a keyframe set is in memory, its tokens lengthen the sequence
    assert any(step[e] > lengths[0][e] for step in lengths for e in range(2))
    probe = agent.new_session(memory_probe="empty")
    empty_lengths, results = _prefill_lengths(agent, probe, frames)
    # BOS + the current frame + the prompt at every step: the same length as at step 0, which has no memory
    assert all(step == empty_lengths[0] for step in empty_lengths) and empty_lengths[0] == lengths[0]
    # only the read is emptied: the episodes still remember their keyframe sets
    assert any(result.memory_sets for step in results for result in step)
    with pytest.raises(ValueError, match="memory_probe='swap'"):
        agent.new_session(memory_probe="swap")


def test_memory_probe_none_is_the_default_session(make_agent):
    agent = memory_agent(make_agent)
    frames = _frames(2, 8, size=agent.model_cfg.vision.image_size)
    _, default = _prefill_lengths(agent, agent.new_session(), frames)
    _, named = _prefill_lengths(agent, agent.new_session(memory_probe="none"), frames)
    for a, b in zip(default, named):
        for x, y in zip(a, b):
            assert x.action == y.action and x.memory_sets == y.memory_sets and x.box == y.box
            assert torch.equal(x.action_logits, y.action_logits)
