"""Activation checkpointing as FSDP applies it (torch's checkpoint wrapper around each block), on the CPU.

`configs/accelerate/fsdp.yaml` asks accelerate for `fsdp_activation_checkpointing`: accelerate wraps every
`LlamaDecoderLayer` and timm ViT `Block` in `torch.distributed.algorithms._checkpoint.checkpoint_wrapper`, so the
model itself does not know its layers are recomputed (transformers' own switch is off). The agent built here
has the 7B preset's module classes at small width: two timm ViTs (DINOv2-style with registers, SigLIP-style)
and a Llama decoder.
"""

from __future__ import annotations

import copy
import dataclasses
import functools

import torch
from timm.models.vision_transformer import Block
from torch.distributed.algorithms._checkpoint.checkpoint_wrapper import (
    CheckpointWrapper,
    apply_activation_checkpointing,
    checkpoint_wrapper,
)
from transformers.models.llama.modeling_llama import LlamaDecoderLayer

WRAPPED_PREFIX = "_checkpoint_wrapped_module."


def wrap_blocks_as_fsdp_does(agent: torch.nn.Module) -> int:
    """Wrap each Llama decoder layer and ViT block as accelerate's FSDP2 path does; returns how many."""
    apply_activation_checkpointing(
        agent,
        checkpoint_wrapper_fn=functools.partial(checkpoint_wrapper, preserve_rng_state=False),
        check_fn=lambda module: isinstance(module, (LlamaDecoderLayer, Block)),
    )
    return sum(isinstance(m, CheckpointWrapper) for m in agent.modules())


def seven_b_like_agent(make_agent, small_config):
    """The small agent with the 7B preset's decoder call: one padded batch (`llm.length_groups: 1`)."""
    llm = dataclasses.replace(small_config().llm, length_groups=1)
    return make_agent(llm=llm).train()


def test_fsdp_style_checkpointing_gives_the_same_loss_and_gradients(make_agent, make_batch, small_config):
    agent = seven_b_like_agent(make_agent, small_config)
    assert agent.model_cfg.vision.type == "tiny" and agent.model_cfg.llm.type == "tiny"
    wrapped = copy.deepcopy(agent)
    # 2 decoder layers + the 2 ViTs' blocks (depth 3, pruned after block depth - 2: 2 blocks each)
    assert wrap_blocks_as_fsdp_does(wrapped) == 2 + 2 + 2
    # transformers' is off
    assert not getattr(wrapped.network.language_model.model, "gradient_checkpointing", False)
    batch = make_batch(agent)

    torch.manual_seed(0)
    loss, logs = agent(batch)
    loss.backward()
    torch.manual_seed(0)
    wrapped_loss, wrapped_logs = wrapped(batch)  # before the fix: the recomputed layer doubled the KV cache
    wrapped_loss.backward()

    torch.testing.assert_close(wrapped_loss, loss)
    assert wrapped_logs["action_accuracy"] == logs["action_accuracy"]
    grads = {name.replace(WRAPPED_PREFIX, ""): p.grad for name, p in wrapped.named_parameters()}
    compared = 0
    for name, param in agent.named_parameters():
        if param.grad is None:
            assert grads[name] is None, name
            continue
        torch.testing.assert_close(grads[name], param.grad, rtol=1e-4, atol=1e-6, msg=name)
        compared += 1
    assert compared > 50  # the ViTs, projector, decoder, LM head and grounding head all got gradients


def test_the_training_forward_never_builds_a_kv_cache(make_agent, make_batch, small_config):
    """The decoder is called with use_cache=False in training, whatever the Llama config's default says."""
    agent = seven_b_like_agent(make_agent, small_config)
    assert agent.network.language_model.config.use_cache  # the model default a plain call would take
    seen = []
    core = agent.network.language_model.model
    hook = core.register_forward_hook(lambda module, args, output: seen.append(output.past_key_values))
    try:
        agent(make_batch(agent))
    finally:
        hook.remove()
    assert seen == [None]


def test_fsdp_preparation_makes_the_tiny_preset_contiguous_with_equal_outputs(tiny_tokenizer):
    """FSDP shards only contiguous parameters, and the tiny preset's ResNet keeps channels-last weights (the
    CPU fast path); train.py makes them contiguous under FSDP only, with the values and outputs unchanged."""
    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.config import tiny_config
    from openfly_agent.training.builder import make_parameters_contiguous

    agent = OpenFlyAgent.from_model_config(tiny_config(), tokenizer=tiny_tokenizer)
    assert agent.model_cfg.vision.type == "tiny-cnn"
    strided = [name for name, p in agent.named_parameters() if not p.is_contiguous()]
    assert strided, "the unsharded tiny preset keeps channels-last weights"
    before = {name: p.detach().clone() for name, p in agent.named_parameters()}
    side = agent.model_cfg.vision.image_size
    frames = torch.randint(0, 256, (2, 3, side, side), dtype=torch.uint8)
    with torch.no_grad():
        reference = agent.network.vision_backbone(frames)
    make_parameters_contiguous(agent)
    assert [name for name, p in agent.named_parameters() if not p.is_contiguous()] == []
    assert all(torch.equal(p, before[name]) for name, p in agent.named_parameters())
    with torch.no_grad():
        torch.testing.assert_close(agent.network.vision_backbone(frames), reference)
