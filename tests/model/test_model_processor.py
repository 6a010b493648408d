"""OpenFlyProcessor: one set of text rules (BOS, suffix, truncation, action target), save / load (also through
AutoProcessor), and the same model inputs for a training batch and an inference step."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_model_session import memory_agent

from openfly_agent import constants as C
from openfly_agent.data.collator import NavigationCollator
from openfly_agent.model.config import BinsActionHeadConfig
from openfly_agent.model.language.action_tokenizer import CODEBOOK
from openfly_agent.model.processor import OpenFlyProcessor

INSTRUCTION = "Fly to the red tower and turn left."
NORM_STATS = {"demo": {"action": {"q01": [0.0] * 8, "q99": CODEBOOK.max(axis=0).tolist()}}}


def _prompt_ids(processor, instruction: str = INSTRUCTION) -> list[int]:
    return list(processor.tokenizer(processor.navigation_prompt(instruction))["input_ids"])


def test_text_rules(make_agent):
    processor = make_agent().processor
    prompt = processor.navigation_prompt(INSTRUCTION)
    assert prompt == f"What action should the drone take to {INSTRUCTION}?"
    plain = _prompt_ids(processor)
    assert plain[0] == processor.tokenizer.bos_token_id  # the BPE tokenizer adds BOS itself
    ids, labels = processor.encode(prompt)
    assert ids == plain and labels == [C.IGNORE_INDEX] * len(plain)  # no action target: the prompt only
    action = processor.action_tokenizer.action_to_token_ids(3)
    ids, labels = processor.encode(prompt, 3)
    assert ids == plain + action and labels == [C.IGNORE_INDEX] * len(plain) + action
    processor.max_length = len(plain) - 2  # too long: the prompt is cut from its end, the action stays
    ids, labels = processor.encode(prompt, 3)
    assert ids == plain[: len(plain) - 3] + action and labels[-1] == action[0]
    processor.max_length = 1
    with pytest.raises(ValueError, match="no room"):
        processor.encode(prompt, 3)


def _word_tokenizer(add_bos: bool):
    """A word-level tokenizer that adds BOS itself or not."""
    from tokenizers import Tokenizer, models, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast

    words = ["<pad>", "<unk>", "<s>", "</s>", "fly", "to", "the", "tower", "?"]
    core = Tokenizer(models.WordLevel({w: i for i, w in enumerate(words)}, unk_token="<unk>"))
    core.pre_tokenizer = pre_tokenizers.WhitespaceSplit()
    if add_bos:
        core.post_processor = processors.TemplateProcessing(single="<s> $A", special_tokens=[("<s>", 2)])
    return PreTrainedTokenizerFast(
        tokenizer_object=core, bos_token="<s>", eos_token="</s>", pad_token="<pad>", unk_token="<unk>"
    )


@pytest.mark.parametrize("add_bos", [True, False])
def test_bos_is_added_once_and_the_suffix_appended(add_bos):
    processor = OpenFlyProcessor(
        _word_tokenizer(add_bos), prompt_template="{instruction} ?", suffix_token_id=8
    )
    action = processor.action_tokenizer.action_to_token_ids(2)
    ids, labels = processor.encode(processor.navigation_prompt("fly to the tower"), 2)
    assert ids == [2, 4, 5, 6, 7, 8] + action  # [BOS] prompt ('?' is the suffix: not appended twice) action
    assert labels == [C.IGNORE_INDEX] * 6 + action
    ids, _ = processor.encode("fly to the", None)
    assert ids == [2, 4, 5, 6, 8]  # inference: the same prompt ids, the suffix appended


def test_bins_target_has_one_eos(make_agent):
    agent = make_agent(action_head=BinsActionHeadConfig(), norm_stats=NORM_STATS)
    processor = agent.processor
    _, labels = processor.encode(processor.navigation_prompt(INSTRUCTION), 1)
    target = [t for t in labels if t != C.IGNORE_INDEX]
    assert (
        len(target) == 9 and target[-1] == processor.tokenizer.eos_token_id and target.count(target[-1]) == 1
    )
    assert processor.decode_action(target[:8]) == 1


def test_batch_call_pads_right(make_agent):
    processor = make_agent().processor
    frames = [np.zeros((20, 30, 3), np.uint8), np.full((56, 56, 3), 9, np.uint8)]
    out = processor(["fly", processor.navigation_prompt(INSTRUCTION)], images=frames, actions=[1, 9])
    assert out["input_ids"].shape == out["attention_mask"].shape == out["labels"].shape
    assert out["pixel_values"].shape == (2, 3, 56, 56) and out["pixel_values"].dtype == torch.uint8
    assert torch.equal(out["pixel_values"][1], processor.image(frames[1]))
    lengths = out["attention_mask"].sum(1).tolist()
    assert lengths[0] < lengths[1]
    assert (out["input_ids"][0, lengths[0] :] == processor.pad_token_id).all()
    assert "labels" not in processor(["fly"])


def test_save_and_load_the_processor(make_agent, tmp_path):
    from transformers import AutoProcessor

    agent = make_agent(action_head=BinsActionHeadConfig(), norm_stats=NORM_STATS)
    agent.save_pretrained(tmp_path)
    saved = json.loads((tmp_path / C.PROCESSOR_CONFIG_NAME).read_text())
    assert saved["image_size"] == agent.model_cfg.vision.image_size and saved["action_stats"] is not None
    loaded = OpenFlyProcessor.from_pretrained(str(tmp_path))
    remote = AutoProcessor.from_pretrained(str(tmp_path), trust_remote_code=True)
    for other in (loaded, remote):
        assert type(other).__name__ == "OpenFlyProcessor"
        assert other.to_dict() == agent.processor.to_dict()
        assert other.encode("fly to the tower", 4) == agent.processor.encode("fly to the tower", 4)


class _Spy:
    """Records the inputs of an agent's text embedding, vision backbone and decoder calls."""

    def __init__(self, agent):
        self.ids, self.pixels, self.llm = [], [], []
        network = agent.network
        embed, vision, llm = network.embed_text, network.vision_backbone.forward_with_cls, network.run_llm
        network.embed_text = lambda ids: (self.ids.append(ids.clone()), embed(ids))[1]
        network.vision_backbone.forward_with_cls = lambda px: (self.pixels.append(px.clone()), vision(px))[1]
        network.run_llm = lambda embeds, mask, **kw: (
            self.llm.append((embeds.clone(), mask.clone())),
            llm(embeds, mask, **kw),
        )[1]  # noqa: E501


def test_training_batch_and_inference_step_feed_the_model_the_same_inputs(make_agent):
    """For the same frame, history and instruction, `forward(collated batch)` and `predict_step` give the model
    the same token ids, masks, pixel values and, through them, the same decoder input (action included)."""
    agent = memory_agent(make_agent)  # the memory fills during a short episode
    rng = np.random.default_rng(4)
    frames = rng.integers(0, 256, (12, 40, 40, 3), dtype=np.uint8)  # not the model's size: resized by both
    obs = lambda t: {"episode_id": "e", "instruction": INSTRUCTION, "rgb": frames[t], "pose": (0, 0, 9, 0)}  # noqa: E731
    spy = _Spy(agent)
    session = agent.new_session()
    steps = 11
    for t in range(steps):
        session.predict_step([obs(t)])
    state = session.episodes["e"]
    memory_sets, boxes = state.memory.sets(), list(state.boxes)  # what step `steps` reads (oldest set first)
    assert memory_sets, "the scripted episode should hold keyframe sets"
    pixels_at = {t: spy.pixels[t][0] for t in range(steps)}  # what the backbone saw when frame t was current
    (result,) = session.predict_step([obs(steps)])
    inference_pixels = spy.pixels[-1][0]
    # the prefill, then (box token) one cached step that embeds the predicted target box
    box_token = agent.network.box_token_embed is not None
    inference_embeds, inference_mask = spy.llm[-2] if box_token else spy.llm[-1]
    if box_token:
        inference_embeds = torch.cat([inference_embeds, spy.llm[-1][0]], dim=1)
        inference_mask = torch.cat([inference_mask, spy.llm[-1][1][:, -1:]], dim=1)

    # the training sample of step `steps`: its memory = the sets the agent holds, with its predicted boxes
    sample = {
        C.OBS_INSTRUCTION: INSTRUCTION,
        C.OBS_RGB: frames[steps],
        C.MEMORY: [[(frames[j], np.asarray(boxes[j]), True) for j in frame_set] for frame_set in memory_sets],
        C.ACTION: result.action,
        # the target box of the step: the one inference predicted, so the box tokens are the same
        C.BOX: np.asarray(result.box, np.float32),
        C.BOX_VISIBLE: result.box_visible,
    }
    cfg = agent.model_cfg
    batch = NavigationCollator(agent.processor, cfg.memory.capacity, cfg.keyframes.set_size)([sample])
    spy.ids.clear(), spy.llm.clear()
    _, logs = agent(batch)
    prompt = state.prompt_ids
    n = len(prompt)
    assert batch[C.INPUT_IDS][0, :n].tolist() == prompt and batch[C.ATTENTION_MASK][0, :n].all()
    assert spy.ids[0][0, :n].tolist() == prompt  # the ids the model embedded
    assert batch[C.LABELS][0, n:].tolist() == agent.processor.action_tokenizer.action_to_token_ids(
        result.action
    )
    assert torch.equal(batch[C.PIXEL_VALUES][0], inference_pixels)
    for k, frame_set in enumerate(memory_sets):  # memory frames: the pixels each had when it was current
        for s, frame in enumerate(frame_set):
            assert torch.equal(batch[C.MEMORY_PIXEL_VALUES][0, k, s], pixels_at[frame])
    # the decoder input: every attended position but the action token, and its mask
    embeds, mask = spy.llm[0]
    attended = embeds[0][mask[0].bool()][:-1]  # (L, D): [BOS] [memory] [current] [prompt] ([BOX])
    assert inference_mask.all() and attended.shape == inference_embeds[0].shape
    torch.testing.assert_close(attended, inference_embeds[0], rtol=1e-5, atol=1e-5)
    assert logs["action_accuracy"] == 1.0  # the prefill's last position predicts the action inference chose
