"""OpenFlyAgent training forward: shapes, token counts, masking invariances, gradients, grounding maths."""

from __future__ import annotations

import math

import pytest
import torch

from openfly_agent.model.config import (
    BoxGroundingConfig,
    CellGroundingConfig,
    MemoryConfig,
    MergingConfig,
    NoGroundingConfig,
    TinyCnnVisionConfig,
    openfly_7b_config,
)
from openfly_agent.model.grounding.head import (
    BoxRegressionHead,
    CellGroundingHead,
    GroundingOutput,
    box_cells,
    cell_centres,
    grounding_loss,
    iou_and_giou,
    windowed_softmax,
)

LOG_KEYS = {"loss", "action_loss", "grounding_loss", "action_accuracy", "box_iou", "num_visible_boxes"}


COLOUR_STATS = {  # tiny-cnn at 64 px with each token's cell colour statistics
    "vision": TinyCnnVisionConfig(
        image_size=64, cnn_channels=[16, 16, 16, 32], cnn_colour_stats=True
    ),  # (narrower ResNets crash oneDNN's channels-last backward in torch 2.13)
    "grounding": CellGroundingConfig(dim=32, num_heads=2),
}


ATTRIBUTES = {
    "grounding": CellGroundingConfig(dim=32, num_heads=2, attribute_weight=1.0)
}  # the attribute loss
VISUAL_SKIP = {  # cells that get the frame's visual tokens
    "grounding": CellGroundingConfig(dim=32, num_heads=2, visual_skip=True)
}
COLOUR_VOCABULARY = {  # cells matched by their colour histograms
    "grounding": CellGroundingConfig(dim=32, num_heads=2, colour_vocabulary=True)
}


@pytest.mark.parametrize(
    "overrides",
    [{}, COLOUR_STATS, ATTRIBUTES, VISUAL_SKIP, COLOUR_VOCABULARY],
    ids=["small", "colour_stats", "attributes", "visual_skip", "colour_vocabulary"],
)  # fmt: skip
def test_forward_backward_reaches_every_parameter(make_agent, make_batch, overrides):
    agent = make_agent(**overrides).train()
    batch = make_batch(agent, batch_size=3)
    if agent.model_cfg.grounding.attribute_weight:  # colour, type, size, feature ids; -1 unknown
        batch["target_attributes"] = torch.tensor([[0, 1, 2, 3], [11, 5, 0, -1], [-1, -1, -1, -1]])
        batch["box_visible"] = torch.tensor([True, True, False])
    loss, logs = agent(batch)
    assert torch.isfinite(loss)
    assert set(logs) >= LOG_KEYS and all(isinstance(v, float) for v in logs.values())
    loss.backward()
    no_grad = [name for name, p in agent.named_parameters() if p.grad is None]
    assert no_grad == []  # DDP-safe: nothing unused


def test_the_colour_vocabulary_reads_the_frame_each_sequence_reads(make_agent, make_batch):
    agent = make_agent(**COLOUR_VOCABULARY)
    batch = make_batch(agent, batch_size=3)
    pixels = batch["pixel_values"]  # (3, 3, H, W)
    pixels[1] = pixels[0]  # rows 0 and 1 read the same frame
    shared = dict(batch, pixel_values=pixels[[0, 2]], frame_index=torch.tensor([0, 0, 1]))
    with torch.no_grad():
        torch.testing.assert_close(agent(shared)[0], agent(batch)[0])
        moved = dict(shared, frame_index=torch.tensor([1, 1, 0]))  # other frames: another loss
        assert not torch.allclose(agent(moved)[0], agent(batch)[0])


def test_visual_token_count_tiny(make_agent, make_batch):
    agent = make_agent()  # 4x4 patches, g = 2 -> 4 tokens per set, K = 2
    memory, memory_mask, current = agent.network.encode(make_batch(agent, batch_size=2))
    assert memory.shape == (2, 2 * 4, agent.network.llm_dim) and memory_mask.shape == (2, 2 * 4)
    assert current.shape == (2, 16, agent.network.llm_dim)
    assert agent.model_cfg.visual_tokens_per_step() == 24


def test_7b_shapes_on_meta_device():
    from openfly_agent.model.agent import OpenFlyAgent

    with torch.device("meta"):
        agent = OpenFlyAgent.from_model_config(openfly_7b_config())
    assert 7.4e9 < sum(p.numel() for p in agent.parameters()) < 7.6e9
    pixels = torch.zeros(2, 3, 224, 224, dtype=torch.uint8, device="meta")
    features = agent.network.vision_backbone(pixels)
    assert features.shape == (2, 256, 2176)
    sets = agent.network.memory.set_tokens(
        agent.network.projector,
        torch.zeros(4, 5, 256, 2176, device="meta"),
        torch.ones(4, 5, dtype=torch.bool, device="meta"),
        torch.zeros(4, 5, 4, device="meta"),
        torch.ones(4, 5, dtype=torch.bool, device="meta"),
    )
    assert sets.shape == (4, 1, 4096)  # (16 / g)^2 = 1 token per keyframe set
    assert features.shape[1] + 2 * sets.shape[1] == 258 == agent.model_cfg.visual_tokens_per_step()
    assert agent.network.language_model.lm_head.weight.shape == (32064, 4096)


def test_missing_memory_sets_contribute_nothing(make_agent, make_batch):
    agent = make_agent()
    batch = make_batch(agent, batch_size=2)
    batch["memory_frame_mask"][:, 1] = False  # set 1 missing everywhere
    loss_two_slots, _ = agent(batch)
    one_slot = dict(batch)
    for key in ("memory_pixel_values", "memory_frame_mask", "memory_boxes", "memory_box_visible"):
        one_slot[key] = batch[key][:, :1]
    loss_one_slot, _ = agent(one_slot)
    swapped = dict(batch)  # the missing set first: positions only count attended tokens
    for key in ("memory_pixel_values", "memory_frame_mask", "memory_boxes", "memory_box_visible"):
        swapped[key] = batch[key].flip(1)
    loss_swapped, _ = agent(swapped)
    torch.testing.assert_close(loss_two_slots, loss_one_slot, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(loss_two_slots, loss_swapped, rtol=1e-5, atol=1e-6)


def test_right_padding_does_not_change_samples(make_agent, make_batch):
    agent = make_agent(grounding=NoGroundingConfig())
    batch = make_batch(agent, batch_size=3)
    loss_all, _ = agent(batch)
    singles = []
    for i in range(3):
        row = {k: v[i : i + 1] for k, v in batch.items()}
        length = int(row["attention_mask"].sum())
        for key in ("input_ids", "attention_mask", "labels"):
            row[key] = row[key][:, :length]
        singles.append(agent(row)[0])
    torch.testing.assert_close(loss_all, torch.stack(singles).mean(), rtol=1e-5, atol=1e-6)


def test_an_agent_without_grounding_head_logs_no_box_iou(make_agent, make_batch):
    agent = make_agent(grounding=NoGroundingConfig())
    _, logs = agent(make_batch(agent, batch_size=2))
    # nothing measured, not an IoU of 0
    assert math.isnan(logs["box_iou"]) and logs["num_visible_boxes"] == 0.0


def test_merging_disabled_and_memory_off(make_agent, make_batch):
    agent = make_agent(merging=MergingConfig(enabled=False))
    loss, _ = agent(make_batch(agent))
    assert torch.isfinite(loss)
    agent = make_agent(memory=MemoryConfig(capacity=0, grid=2))
    batch = make_batch(agent, capacity=0)
    memory, _, current = agent.network.encode(batch)
    assert memory.shape[1] == 0 and current.shape[1] == 16
    assert torch.isfinite(agent(batch)[0])


def test_bad_batches_are_clear_errors(make_agent, make_batch):
    agent = make_agent()
    batch = make_batch(agent)
    with pytest.raises(ValueError, match="memory sets but memory.capacity is 2"):
        agent(make_batch(agent, capacity=3))
    wrong = dict(batch, pixel_values=batch["pixel_values"].float())
    with pytest.raises(ValueError, match="uint8 RGB pixels"):
        agent(wrong)
    no_bos = dict(batch, input_ids=batch["input_ids"].roll(1, dims=1))
    with pytest.raises(ValueError, match="start with BOS"):
        agent(no_bos)


@pytest.mark.parametrize(
    ("pred", "target", "iou", "giou"),
    [
        ((0.5, 0.5, 0.4, 0.4), (0.5, 0.5, 0.4, 0.4), 1.0, 1.0),  # identical
        ((0.5, 0.5, 0.4, 0.4), (0.5, 0.5, 0.8, 0.8), 0.25, 0.25),  # nested: hull = outer box
        ((0.1, 0.1, 0.2, 0.2), (0.7, 0.7, 0.2, 0.2), 0.0, -0.875),  # disjoint: 0 - (0.64 - 0.08) / 0.64
        ((0.3, 0.5, 0.4, 0.2), (0.5, 0.5, 0.4, 0.2), 1 / 3, 1 / 3),  # half overlap: 0.04 / 0.12
    ],
)
def test_giou_by_hand(pred, target, iou, giou):
    got_iou, got_giou = iou_and_giou(torch.tensor([pred]), torch.tensor([target]))
    assert got_iou.item() == pytest.approx(iou, abs=1e-6)
    assert got_giou.item() == pytest.approx(giou, abs=1e-6)


def test_grounding_loss_ignores_invisible_targets():
    cfg = BoxGroundingConfig(l1_weight=2.0, visibility_weight=0.0)
    pred = GroundingOutput(torch.tensor([[0.5, 0.5, 0.4, 0.4], [0.5, 0.5, 0.2, 0.2]]), torch.zeros(2))
    target = torch.tensor([[0.5, 0.5, 0.8, 0.8], [0.1, 0.1, 0.1, 0.1]])
    visible = torch.tensor([True, False])
    loss, logs = grounding_loss(pred, target, visible, cfg)
    # only row 0: (1 - GIoU) = 0.75, L1 = 0.4 + 0.4 -> 0.75 + 2 * 0.8
    assert loss.item() == pytest.approx(0.75 + 1.6, abs=1e-6)
    assert logs["box_iou"] == pytest.approx(0.25) and logs["num_visible_boxes"] == 1.0
    target[1] = torch.tensor([0.9, 0.9, 0.05, 0.05])
    assert grounding_loss(pred, target, visible, cfg)[0].item() == pytest.approx(loss.item())
    none_visible, logs = grounding_loss(pred, target, torch.tensor([False, False]), cfg)
    assert none_visible.item() == 0.0 and logs["box_iou"] == 0.0


def test_grounding_head_outputs_unit_boxes():
    head = BoxRegressionHead(24, BoxGroundingConfig(dim=16, num_heads=2))
    hidden = torch.randn(2, 7, 24) * 10
    mask = torch.tensor([[True] * 7, [True] * 3 + [False] * 4])
    out = head(hidden, mask)
    assert out.boxes.shape == (2, 4) and out.visibility.shape == (2,) and out.cell_logits is None
    assert ((out.boxes > 0) & (out.boxes < 1)).all()
    hidden2 = hidden.clone()
    hidden2[1, 3:] = 1e3  # masked positions do not matter
    torch.testing.assert_close(head(hidden2, mask).boxes[1], out.boxes[1])


def _fit_head(head, inputs, targets, cfg, steps: int) -> dict[str, float]:
    """Adam (lr 1e-2) on the grounding loss of `head(*inputs)` against `targets` (all visible); the last logs."""
    optimizer = torch.optim.Adam(head.parameters(), lr=1e-2)
    for _ in range(steps):
        loss, logs = grounding_loss(head(*inputs), targets, torch.ones(len(targets), dtype=torch.bool), cfg)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return logs


def test_cell_head_centres_the_box_on_its_cells_and_learns_the_right_cell():
    torch.manual_seed(0)
    cfg = CellGroundingConfig(dim=16, num_heads=2)
    head = CellGroundingHead(24, cfg, grid_side=2)
    with pytest.raises(ValueError, match="grid side"):
        CellGroundingHead(24, CellGroundingConfig(dim=16, num_heads=2), grid_side=0)
    # sequence: 4 image tokens (a 2 x 2 grid) then 2 prompt tokens; the prompt's last token names the cell
    hidden = torch.randn(4, 6, 24)
    hidden[:, :4] += torch.eye(4, 24) * 3  # each cell has its own feature
    target_cell = torch.tensor([0, 1, 2, 3])
    hidden[:, 5] = torch.eye(4, 24)[target_cell] * 3
    mask = torch.ones(4, 6, dtype=torch.bool)
    image = torch.arange(4).expand(4, 4)
    last = torch.full((4,), 5)
    centres = torch.tensor([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]])
    targets = torch.cat([centres[target_cell], torch.full((4, 2), 0.3)], dim=1)
    logs = _fit_head(head, (hidden, mask, image, last), targets, cfg, 150)
    out = head(hidden, mask, image, last)
    assert out.cell_logits.argmax(-1).tolist() == target_cell.tolist()
    assert logs["box_iou"] > 0.8
    assert box_cells(out.boxes, 2).tolist() == target_cell.tolist()


def test_windowed_softmax_keeps_the_cells_around_the_best_one():
    logits = torch.tensor([[3.0, 1.0, 0.0, 1.0, 2.0, 0.0, 0.0, 0.0, 2.5]])  # 3 x 3, best cell 0 (top left)
    torch.testing.assert_close(windowed_softmax(logits, 3, None), logits.softmax(-1))
    assert windowed_softmax(logits, 3, 0).tolist() == [[1.0] + [0.0] * 8]
    near = torch.tensor([3.0, 1.0, 1.0, 2.0]).exp()  # cells 0, 1, 3, 4: the 2 x 2 corner of the 3 x 3 window
    expected = torch.zeros(9)
    expected[[0, 1, 3, 4]] = near / near.sum()
    torch.testing.assert_close(windowed_softmax(logits, 3, 1)[0], expected)
    # a window that covers the grid: the plain softmax
    torch.testing.assert_close(windowed_softmax(logits, 3, 2), logits.softmax(-1))


def test_a_centre_window_picks_one_of_two_peaks_instead_of_their_middle():
    logits = torch.full((1, 9), -10.0)
    # two landmarks scored almost alike, in opposite corners of a 3 x 3 grid
    logits[0, 0], logits[0, 8] = 5.0, 4.9
    centres = cell_centres(3)
    everywhere = windowed_softmax(logits, 3, None) @ centres
    around_best = windowed_softmax(logits, 3, 1) @ centres
    assert 0.4 < float(everywhere[0, 0]) < 0.5 and 0.4 < float(everywhere[0, 1]) < 0.5  # between the two
    torch.testing.assert_close(around_best, torch.tensor([[1 / 6, 1 / 6]]), atol=1e-4, rtol=0)  # on the best
    with pytest.raises(ValueError, match="centre_window"):
        CellGroundingConfig(centre_window=-1)


def test_the_centre_window_is_a_decoding_rule_training_reads_every_cell():
    torch.manual_seed(0)
    head = CellGroundingHead(24, CellGroundingConfig(dim=16, num_heads=2, centre_window=1), grid_side=4)
    hidden = torch.randn(8, 18, 24)  # 16 image tokens (a 4 x 4 grid), then 2 prompt tokens
    inputs = (
        hidden,
        torch.ones(8, 18, dtype=torch.bool),
        torch.arange(16).expand(8, 16),
        torch.full((8,), 17),
    )
    head.eval()
    windowed = head(*inputs)
    head.centre_window = None
    everywhere = head(*inputs)
    head.train()
    head.centre_window = 1
    training = head(*inputs)
    torch.testing.assert_close(training.boxes, everywhere.boxes)  # ignored in training
    assert not torch.allclose(windowed.boxes, everywhere.boxes)  # applied at inference
    # the scores themselves unchanged
    torch.testing.assert_close(windowed.cell_logits, everywhere.cell_logits)
    assert CellGroundingConfig().centre_window == 1  # the tiny preset's default


def test_activation_checkpointing_gives_the_same_gradients(make_agent, make_batch):
    from openfly_agent.training.modes import switch_on_decoder_checkpointing

    agent = make_agent().train()
    batch = make_batch(agent)
    torch.manual_seed(0)  # the same box-token jitter in both passes
    agent(batch)[0].backward()
    plain = {n: p.grad.clone() for n, p in agent.named_parameters()}
    agent.zero_grad()
    switch_on_decoder_checkpointing(agent)  # the transformers name that exists (5.17 lacks the new one)
    assert agent.network.vision_backbone.featurizer.grad_checkpointing
    torch.manual_seed(0)
    agent(batch)[0].backward()
    for name, param in agent.named_parameters():
        torch.testing.assert_close(param.grad, plain[name], rtol=1e-4, atol=1e-6, msg=name)


def test_bfloat16_forward(make_agent, make_batch):
    agent = make_agent().to(torch.bfloat16)
    loss, logs = agent(make_batch(agent))
    assert loss.dtype == torch.float32 and torch.isfinite(loss)


def test_tiny_preset_forward(tiny_tokenizer, make_batch):
    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.config import tiny_config

    agent = OpenFlyAgent.from_model_config(tiny_config(), tokenizer=tiny_tokenizer)
    assert agent.model_cfg.llm.vocab_size == len(tiny_tokenizer) + 256
    assert agent.action_tokenizer.discrete_token_ids[0] == len(tiny_tokenizer)  # first reserved id
    batch = make_batch(agent, batch_size=2)
    memory, _, current = agent.network.encode(batch)
    # K = 2 sets of (8 / 8)^2 tokens, 8x8 patches
    assert (memory.shape, current.shape) == ((2, 2, 128), (2, 64, 128))
    loss, _ = agent(batch)
    assert torch.isfinite(loss)
