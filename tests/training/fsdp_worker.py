"""One rank of the CPU FSDP2 check (tests/training/test_fsdp_cpu.py), started by torchrun over gloo.

    torchrun --standalone --nproc_per_node 2 tests/training/fsdp_worker.py --tokenizer DIR --out DIR

For each model (the tiny preset's ResNet + Llama; the 7B preset's classes at small width: two timm ViTs and a
Llama decoder), as accelerate's FSDP2 path prepares it (configs/accelerate/fsdp.yaml): each Llama decoder layer
and ViT block in torch's checkpoint wrapper, then `fully_shard` on each of them and on the root. Every rank
trains on the same batch, so the sharded run must follow an unsharded copy step for step. Then the sharded
state (weights + AdamW) is saved with torch.distributed.checkpoint, loaded into a freshly built sharded model,
compared, and both take one more step. Rank 0 writes `<out>/<model>.json` with the figures the test checks.
"""

from __future__ import annotations

import argparse
import copy
import functools
import json
import sys
from pathlib import Path

import torch
import torch.distributed as dist
import torch.distributed.checkpoint as dcp
from torch.distributed.algorithms._checkpoint.checkpoint_wrapper import (
    apply_activation_checkpointing,
    checkpoint_wrapper,
)
from torch.distributed.checkpoint.state_dict import (
    get_model_state_dict,
    get_optimizer_state_dict,
    set_model_state_dict,
    set_optimizer_state_dict,
)
from torch.distributed.fsdp import fully_shard
from torch.distributed.tensor import DTensor

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT))

from bench.train_throughput import synthetic_batch  # noqa: E402
from openfly_agent.model.agent import OpenFlyAgent  # noqa: E402
from openfly_agent.model.config import (  # noqa: E402
    CellGroundingConfig,
    DiscreteActionHeadConfig,
    MemoryConfig,
    TinyCnnVisionConfig,
    TinyLLMConfig,
    TinyVitVisionConfig,
    tiny_config,
)
from openfly_agent.model.language.tokenizer import load_tokenizer  # noqa: E402
from openfly_agent.training.builder import make_parameters_contiguous  # noqa: E402

STEPS = 3
LR = 1e-3
MODELS = {
    # tiny-cnn (whose 7 x 7 stem FSDP refused while it was channels-last) at 64 px, no random box-token jitter
    "tiny": tiny_config(
        vision=TinyCnnVisionConfig(image_size=64, cnn_channels=[16, 16, 16, 32]),
        memory=MemoryConfig(capacity=2, grid=4),
        action_head=DiscreteActionHeadConfig(box_token_jitter=0.0),
    ),
    "vit-llama": tiny_config(  # the 7B preset's module classes, the 7B layout (no box token, one decoder call)
        vision=TinyVitVisionConfig(
            image_size=56, patch_size=14, width=32, fused_width=48, depth=3, num_heads=2
        ),
        llm=TinyLLMConfig(hidden_size=64, num_layers=2, num_heads=2, intermediate_size=128, length_groups=1),
        grounding=CellGroundingConfig(dim=32, num_heads=2),
        memory=MemoryConfig(capacity=2, grid=2),
        action_head=DiscreteActionHeadConfig(box_token=False),
    ),
}


def wrapped_classes() -> tuple[type, ...]:
    """configs/accelerate/fsdp.yaml's `fsdp_transformer_layer_cls_to_wrap: LlamaDecoderLayer,Block`."""
    from timm.models.vision_transformer import Block
    from transformers.models.llama.modeling_llama import LlamaDecoderLayer

    return LlamaDecoderLayer, Block


def shard(agent: torch.nn.Module) -> torch.nn.Module:
    """Checkpoint-wrap and `fully_shard` each transformer block, then the root (accelerate's FSDP2 order), after
    the layout fix train.py applies under FSDP (`make_parameters_contiguous`)."""
    classes = wrapped_classes()
    make_parameters_contiguous(agent)
    apply_activation_checkpointing(
        agent,
        checkpoint_wrapper_fn=functools.partial(checkpoint_wrapper, preserve_rng_state=False),
        check_fn=lambda module: isinstance(module, classes),
    )
    for module in list(agent.modules()):
        if isinstance(module, classes):
            fully_shard(module)
    fully_shard(agent)
    return agent


def full(tensor: torch.Tensor) -> torch.Tensor:
    return tensor.full_tensor() if isinstance(tensor, DTensor) else tensor


def full_state(model, optimizer) -> dict[str, torch.Tensor]:
    """Weights and AdamW states as full tensors, keyed by parameter name (wrapper prefixes removed)."""
    state = {f"param/{k}": full(v).detach().clone() for k, v in get_model_state_dict(model).items()}
    for name, values in get_optimizer_state_dict(model, optimizer)["state"].items():
        for key, value in values.items():
            state[f"optim/{name}/{key}"] = full(torch.as_tensor(value)).detach().clone()
    return state


def max_difference(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    assert a.keys() == b.keys(), sorted(set(a) ^ set(b))[:5]
    return max(float((a[k].float() - b[k].float()).abs().max()) for k in a)


def train_step(model, optimizer, batch) -> float:
    loss, _ = model(batch)
    loss.backward()
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    return float(loss.detach())


def build(model_name: str, tokenizer) -> OpenFlyAgent:
    torch.manual_seed(0)
    return OpenFlyAgent.from_model_config(MODELS[model_name], tokenizer=tokenizer).train()


def run(model_name: str, tokenizer, out: Path) -> dict:
    rank = dist.get_rank()
    agent = build(model_name, tokenizer)
    reference = copy.deepcopy(agent)  # unsharded, trained on the same batch in this process
    batch = synthetic_batch(agent, 2, frame_px=agent.model_cfg.vision.image_size, seed=0)
    model = shard(agent)
    optimizer = torch.optim.AdamW(model.parameters(), lr=LR)
    reference_optimizer = torch.optim.AdamW(reference.parameters(), lr=LR)
    sharded_params = [p for p in model.parameters() if isinstance(p, DTensor)]
    local = sum(p.to_local().numel() for p in sharded_params)
    total = sum(p.numel() for p in sharded_params)

    losses, reference_losses = [], []
    for _ in range(STEPS):
        losses.append(train_step(model, optimizer, batch))
        reference_losses.append(train_step(reference, reference_optimizer, batch))
    reference_state = {k: v.detach() for k, v in reference.state_dict().items()}
    trained = {k.removeprefix("param/"): v for k, v in full_state(model, optimizer).items() if "param/" in k}
    weights_vs_unsharded = max_difference(trained, reference_state)

    checkpoint = out / f"{model_name}-dcp"
    dcp.save(
        {"model": get_model_state_dict(model), "optim": get_optimizer_state_dict(model, optimizer)},
        checkpoint_id=str(checkpoint),
    )
    saved = full_state(model, optimizer)

    resumed = shard(build(model_name, tokenizer))  # fresh weights, fresh optimizer: all must come from disk
    resumed_optimizer = torch.optim.AdamW(resumed.parameters(), lr=LR)
    train_step(
        resumed, resumed_optimizer, batch
    )  # give the fresh optimizer states that the load must replace
    state = {
        "model": get_model_state_dict(resumed),
        "optim": get_optimizer_state_dict(resumed, resumed_optimizer),
    }
    dcp.load(state, checkpoint_id=str(checkpoint))
    set_model_state_dict(resumed, state["model"])
    set_optimizer_state_dict(resumed, resumed_optimizer, state["optim"])
    resumed_vs_saved = max_difference(full_state(resumed, resumed_optimizer), saved)

    next_loss = train_step(model, optimizer, batch)
    next_resumed_loss = train_step(resumed, resumed_optimizer, batch)
    after_step = max_difference(full_state(resumed, resumed_optimizer), full_state(model, optimizer))
    return {
        "rank": rank,
        "world_size": dist.get_world_size(),
        "sharded_params": len(sharded_params),
        "local_fraction": local / total,
        "losses": losses,
        "reference_losses": reference_losses,
        "weights_vs_unsharded": weights_vs_unsharded,
        "resumed_vs_saved": resumed_vs_saved,
        "saved_tensors": len(saved),
        "next_loss": next_loss,
        "next_resumed_loss": next_resumed_loss,
        "after_step_difference": after_step,
        "checkpoint_files": sorted(p.name for p in checkpoint.iterdir()),
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--tokenizer", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--models", default=",".join(MODELS))
    args = parser.parse_args()
    dist.init_process_group("gloo")
    torch.set_num_threads(1)
    tokenizer = load_tokenizer(args.tokenizer)
    out = Path(args.out)
    for name in args.models.split(","):
        result = run(name, tokenizer, out)
        if dist.get_rank() == 0:
            (out / f"{name}.json").write_text(json.dumps(result, indent=1))
    dist.barrier()
    dist.destroy_process_group()


if __name__ == "__main__":
    main()
