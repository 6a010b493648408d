"""The model on CUDA (skipped without a GPU): the same losses as on the CPU, a bf16 autocast training step, and
closed-loop actions equal to the CPU's."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from openfly_agent.model.config import TinyCnnVisionConfig

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")]

INSTRUCTIONS = [
    "Fly to the red tower and turn left.",
    "Ascend above the white house, then stop near the dome.",
]


def _on(batch: dict, device: str) -> dict:
    return {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


@pytest.mark.parametrize("backbone", ["vit", "tiny-cnn"])
def test_cuda_forward_gives_the_cpu_losses(backbone, make_agent, make_batch, tiny_tokenizer):
    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.config import tiny_config

    torch.manual_seed(0)
    if backbone == "vit":
        agent = make_agent()
    else:  # the tiny preset as trained: the ResNet backbone at 128 px
        agent = OpenFlyAgent.from_model_config(tiny_config(), tokenizer=tiny_tokenizer).eval()
    batch = make_batch(agent)
    with torch.no_grad():
        cpu_loss, cpu_logs = agent(batch)
        cuda_loss, cuda_logs = agent.to("cuda")(_on(batch, "cuda"))
    assert cuda_loss.device.type == "cuda"
    torch.testing.assert_close(cuda_loss.cpu(), cpu_loss, rtol=1e-3, atol=1e-4)
    for key in ("action_loss", "grounding_loss", "box_iou"):
        assert cuda_logs[key] == pytest.approx(cpu_logs[key], rel=1e-3, abs=1e-4), key


def test_cuda_bf16_autocast_step_trains_every_tensor_with_a_gradient(make_agent, make_batch):
    agent = make_agent().train().to("cuda")
    batch = _on(make_batch(agent), "cuda")
    before = {n: p.detach().clone() for n, p in agent.named_parameters()}
    with torch.autocast("cuda", dtype=torch.bfloat16):
        loss, _ = agent(batch)
    loss.backward()
    with_grad = {n for n, p in agent.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
    assert torch.isfinite(loss) and len(with_grad) > 0
    assert all(torch.isfinite(p.grad).all() for p in agent.parameters() if p.grad is not None)
    torch.optim.AdamW(agent.parameters(), lr=1e-3).step()
    unchanged = {n for n, p in agent.named_parameters() if torch.equal(p.detach(), before[n])}
    assert not (with_grad & unchanged)


def test_cuda_closed_loop_actions_equal_the_cpu_ones(make_agent):
    """Two episodes over 5 steps with keyframe memory (greedy decoding): the same actions on both devices."""
    frames = np.random.default_rng(0).integers(0, 256, (2, 5, 56, 56, 3), dtype=np.uint8)

    def fly(agent) -> list[list[int]]:
        session = agent.new_session()
        return [
            session.select_action(
                [{"episode_id": f"ep{e}", "instruction": INSTRUCTIONS[e], "rgb": frames[e, t], "pose": (0.0, 0.0, 10.0, 0.0)}
                 for e in range(2)]
            )
            for t in range(frames.shape[1])
        ]  # fmt: skip

    agent = make_agent(seed=1)
    with torch.no_grad():
        agent.network.projector.fc3.weight.mul_(10.0)  # actions that change with the image
    on_cpu = fly(agent)
    assert len({a for step in on_cpu for a in step}) > 1  # not a constant policy, so equality means something
    assert fly(agent.to("cuda")) == on_cpu


def test_cuda_patch_stem_gives_the_cpu_values():
    from openfly_agent.model.vision.conv import ConvVisionBackbone

    generator = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    backbone = ConvVisionBackbone(TinyCnnVisionConfig(cnn_stem="patch4", cnn_colour_stats=True)).eval()
    pixels = torch.randint(0, 256, (2, 3, 128, 128), dtype=torch.uint8, generator=generator)
    with torch.no_grad():
        cpu_tokens = backbone(pixels)
        cuda_tokens = backbone.cuda()(pixels.cuda())
    torch.testing.assert_close(cuda_tokens.cpu(), cpu_tokens, rtol=1e-3, atol=1e-3)
