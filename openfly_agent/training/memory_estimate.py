"""Per-GPU memory a training run needs, estimated from its config before any weight is read.

The parameter counts come from the agent built on the meta device (no memory, no compute) with the run's freeze
stage or LoRA adapters applied; the rest is arithmetic on those counts and the config (docs/TRAINING.md,
"Memory"). Per GPU, in bytes:

- model states: fp32 weights (4 B / parameter), fp32 gradients and AdamW's two fp32 moments of the trainable
  parameters (4 + 8 B), divided over the processes as the launcher shards them (FSDP: all three; ZeRO-2:
  gradients and moments; ZeRO-3: all) or moved to host memory (FSDP CPU offload: all three; ZeRO's
  `offload_optimizer_device: cpu`: the moments). DeepSpeed keeps bf16 weights on the GPU (2 B).
- AdamW's step on the GPU (`foreach`, the CUDA default) holds one more fp32 copy of its trainable shard.
- bf16 autocast caches a bf16 copy of every trainable fp32 weight from the forward to the backward (not under
  FSDP / DeepSpeed, whose weights are already bf16).
- FSDP gathers the full bf16 weights of the modules it does not wrap (embeddings, LM head, projector, heads) and
  of two wrapped blocks at a time (the running one and the prefetched one).
- activations of one micro-batch with every memory slot filled: the tensors the Llama layers, the trained ViT
  blocks and the projector keep for the backward (counted per token from the module widths), only the block
  inputs under activation checkpointing (plus one block's working set, recomputed).
- 1 GiB for the CUDA context and the allocator's slack.

It is a lower bound of the peak, not a prediction: the allocator's fragmentation and transient buffers are not
modelled. Measured on one H200, the LoRA recipe peaked at 54.5 GiB where this estimate gives 33.1 GiB (61 %); the
full fine-tune under FSDP on one GPU ran out of memory in its first AdamW step, where this estimate gives
140.7 GiB (docs/TRAINING.md, "Memory"). A run is refused when the estimate alone exceeds the GPU, or when the
model states it offloads exceed `HOST_MEMORY_USABLE` of the host's memory (the kernel kills such a run without a
message: measured, below).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import torch

from openfly_agent.training.config import TrainConfig
from openfly_agent.training.modes import apply_training_mode
from openfly_agent.training.preflight import PreflightError
from openfly_agent.utils.cli_options import config_path_of

logger = logging.getLogger(__name__)

GIB = 2**30
FP32, BF16 = 4, 2
ADAM_STATE_BYTES = 8  # exp_avg + exp_avg_sq in fp32
CUDA_RESERVE_BYTES = 1 * GIB  # CUDA context, cuBLAS workspace, allocator slack
# text tokens after the visual ones: BOS, the prompt template and a ~70-word instruction, the action (the 7B
# LoRA bench's samples had 357 LLM tokens with 258 visual ones: docs/BENCHMARKS.md)
TEXT_TOKENS = 100
SHARDING_NONE, SHARDING_FSDP, SHARDING_ZERO2, SHARDING_ZERO3 = "none", "fsdp", "zero2", "zero3"
# The share of the host's memory that offloaded model states may take. On one H200 machine with 128 GiB of RAM,
# the full fine-tune under fsdp_offload.yaml (111.8 GiB of offloaded states by this estimate, 87 %) was killed
# by the kernel (SIGKILL, no message) in its first step, 2026-11-27: the process, the CUDA libraries, the loaded
# checkpoint and the data workers need the rest.
HOST_MEMORY_USABLE = 0.85
CGROUP_MEMORY_LIMIT = "/sys/fs/cgroup/memory.max"  # cgroup v2: a container's limit, or "max"


@dataclass(frozen=True)
class Sharding:
    """How the launch spreads the model states (from the accelerate config the run was launched with).

    Attributes:
        kind: `none` (one process, or DDP replicas), `fsdp` (full shard), `zero2`, `zero3`.
        world_size: processes of the launch.
        offload: FSDP: weights, gradients and optimizer states in host memory; ZeRO: the optimizer states.
        activation_checkpointing: the launcher checkpoints each block (FSDP's `fsdp_activation_checkpointing`).
    """

    kind: str = SHARDING_NONE
    world_size: int = 1
    offload: bool = False
    activation_checkpointing: bool = False


def sharding_of(accelerator) -> Sharding:
    """The `Sharding` of an `accelerate.Accelerator`."""
    from accelerate.utils import DistributedType

    world = accelerator.num_processes
    if accelerator.distributed_type == DistributedType.FSDP:
        return fsdp_sharding(accelerator.state.fsdp_plugin, world)
    if accelerator.distributed_type == DistributedType.DEEPSPEED:
        plugin = accelerator.state.deepspeed_plugin
        offload = plugin.deepspeed_config.get("zero_optimization", {}).get("offload_optimizer", {})
        kind = SHARDING_ZERO3 if int(plugin.zero_stage) == 3 else SHARDING_ZERO2
        return Sharding(kind, world, offload.get("device", "none") == "cpu")
    return Sharding(SHARDING_NONE, world)


def fsdp_sharding(plugin, world_size: int) -> Sharding:
    """The `Sharding` of accelerate's `FullyShardedDataParallelPlugin` (FSDP2: `CPUOffloadPolicy` offloads;
    FSDP1: `CPUOffload(offload_params=True)`)."""
    offload = plugin.cpu_offload
    offloaded = type(offload).__name__ == "CPUOffloadPolicy" or bool(
        getattr(offload, "offload_params", False)
    )
    return Sharding(SHARDING_FSDP, world_size, offloaded, bool(plugin.activation_checkpointing))


@dataclass(frozen=True)
class ModelSizes:
    """What the estimate reads from the agent a config builds (counted on the meta device).

    Attributes:
        params: every parameter.
        trainable: parameters that get gradients (the freeze stage, or the LoRA adapters + projector + heads).
        largest_block: parameters of the largest Llama decoder layer or ViT block (FSDP's wrapped units).
        unwrapped: parameters outside those blocks (FSDP gathers them for the whole forward).
        llm_layers / llm_hidden / llm_intermediate: the decoder's shape.
        vit_blocks: (width, MLP width, tokens per frame) of each ViT block that trains.
        projector_widths: input width and each Linear's output width of the projector.
        tokens_per_sample: LLM tokens of one sample with every memory slot filled.
        frames_per_sample: frames the vision backbone encodes per sample (current + K sets of S).
        patches_per_frame: P, the projector's tokens per frame.
    """

    params: int
    trainable: int
    largest_block: int
    unwrapped: int
    llm_layers: int
    llm_hidden: int
    llm_intermediate: int
    vit_blocks: tuple[tuple[int, int, int], ...]
    projector_widths: tuple[int, ...]
    tokens_per_sample: int
    frames_per_sample: int
    patches_per_frame: int


def model_sizes(cfg: TrainConfig) -> ModelSizes:
    """Count the parameters of the agent `cfg` trains, built on the meta device with its freeze stage / LoRA.

    The tiny LLM sizes its vocabulary from the tokenizer; without one it is taken as `tokenizer.train_vocab_size`
    plus the 256 action ids (a few thousand parameters either way).
    """
    from timm.models.vision_transformer import Block, VisionTransformer
    from transformers.models.llama.modeling_llama import LlamaDecoderLayer

    from openfly_agent.model.agent import OpenFlyAgent  # lazy: transformers

    llm = dataclasses.replace(
        cfg.model.llm, tokenizer_path=None
    )  # nothing is read: the builder checks it later
    if llm.vocab_size is None and llm.trains_own_tokenizer:
        llm = dataclasses.replace(llm, vocab_size=llm.default_vocab_size(cfg.tokenizer.train_vocab_size))
    model_cfg = dataclasses.replace(cfg.model, llm=llm)
    with torch.device("meta"):
        agent = OpenFlyAgent.from_model_config(model_cfg)
        apply_training_mode(
            agent,
            dataclasses.replace(cfg, model=model_cfg, gradient_checkpointing=False, compile_layers=False),
        )
    blocks = [m for m in agent.modules() if isinstance(m, (LlamaDecoderLayer, Block))]
    block_sizes = [sum(p.numel() for p in b.parameters()) for b in blocks]
    params = sum(p.numel() for p in agent.parameters())
    vit_blocks = []
    for vit in (m for m in agent.modules() if isinstance(m, VisionTransformer)):
        tokens = model_cfg.vision.num_patches + vit.num_prefix_tokens
        for block in vit.blocks:
            if isinstance(block, Block) and any(p.requires_grad for p in block.parameters()):
                vit_blocks.append((block.norm1.normalized_shape[0], block.mlp.fc1.out_features, tokens))
    linears = [m for m in agent.network.projector.modules() if isinstance(m, torch.nn.Linear)]
    config = agent.network.language_model.config
    return ModelSizes(
        params=params,
        trainable=sum(p.numel() for p in agent.parameters() if p.requires_grad),
        largest_block=max(block_sizes, default=0),
        unwrapped=params - sum(block_sizes),
        llm_layers=config.num_hidden_layers,
        llm_hidden=config.hidden_size,
        llm_intermediate=config.intermediate_size,
        vit_blocks=tuple(vit_blocks),
        projector_widths=(linears[0].in_features, *(m.out_features for m in linears)) if linears else (),
        tokens_per_sample=model_cfg.visual_tokens_per_step() + TEXT_TOKENS,
        frames_per_sample=1 + model_cfg.memory.capacity * model_cfg.keyframes.set_size,
        patches_per_frame=model_cfg.vision.num_patches,
    )


@dataclass(frozen=True)
class MemoryEstimate:
    """Bytes per GPU by part (see the module docstring), and what goes to host memory with offload."""

    weights: int
    gradients: int
    optimizer: int
    optimizer_step: int
    autocast_cache: int
    gathered: int
    activations: int
    host: int
    reserve: int = CUDA_RESERVE_BYTES

    @property
    def peak(self) -> int:
        """The larger of the forward / backward peak and the optimizer step's, plus the reserve."""
        backward = (
            self.weights
            + self.optimizer
            + self.gathered
            + max(self.activations + self.autocast_cache, self.gradients)
        )
        step = self.weights + self.gradients + self.optimizer + self.optimizer_step
        return max(backward, step) + self.reserve

    def summary(self) -> str:
        """`37.1 GiB per GPU (weights 28.2, gradients 0.6, ...)`: the one-line form the run logs."""
        parts = {
            "weights": self.weights,
            "gradients": self.gradients,
            "AdamW states": self.optimizer,
            "AdamW step": self.optimizer_step,
            "autocast copies": self.autocast_cache,
            "FSDP gathered": self.gathered,
            "activations": self.activations,
        }
        listed = ", ".join(f"{name} {value / GIB:.1f}" for name, value in parts.items() if value)
        host = f"; {self.host / GIB:.1f} GiB in host memory" if self.host else ""
        return f"{self.peak / GIB:.1f} GiB per GPU ({listed}, CUDA reserve {self.reserve / GIB:.1f}){host}"


def activation_bytes(sizes: ModelSizes, batch: int, checkpointing: bool, residual_bytes: int) -> int:
    """Bytes the backward keeps from the forward of a micro-batch of `batch` samples.

    Per token, a Llama layer keeps its two RMSNorm inputs (residual dtype), the norms' outputs, q / k / v, the
    attention output (bf16) and the MLP's gate, up, activation and product: 2 r h + 8 h + 8 I bytes (r the
    residual's bytes). A ViT block keeps 2 r w + 8 w + 4 M (no gate). Checkpointed, a block keeps its input
    (r h per token) and one block's working set is alive while it is recomputed.
    """
    tokens = batch * sizes.tokens_per_sample
    frames = batch * sizes.frames_per_sample
    h, inter = sizes.llm_hidden, sizes.llm_intermediate
    llm_layer = tokens * (2 * residual_bytes * h + 8 * h + 8 * inter)
    vit_layers = [frames * t * (2 * residual_bytes * w + 8 * w + 4 * m) for w, m, t in sizes.vit_blocks]
    if checkpointing:
        kept = sizes.llm_layers * tokens * residual_bytes * h + max([llm_layer, *vit_layers])
        kept += sum(frames * t * residual_bytes * w for w, _, t in sizes.vit_blocks)
    else:
        kept = sizes.llm_layers * llm_layer + sum(vit_layers)
    # the projector on every frame's patches: each Linear's input, in bf16
    patches = frames * sizes.patches_per_frame
    kept += patches * BF16 * sum(sizes.projector_widths[:-1])
    return int(kept)


def estimate_memory(sizes: ModelSizes, cfg: TrainConfig, sharding: Sharding) -> MemoryEstimate:
    """Per-GPU bytes of a run of `cfg` whose agent has `sizes`, launched as `sharding` says."""
    world = sharding.world_size
    params, trainable = sizes.params, sizes.trainable
    mixed = cfg.precision in ("bf16", "fp16")
    checkpointing = cfg.gradient_checkpointing or sharding.activation_checkpointing
    gathered = host = autocast = 0
    if sharding.kind == SHARDING_FSDP:
        weights, gradients = FP32 * params // world, FP32 * trainable // world
        optimizer, step = ADAM_STATE_BYTES * trainable // world, FP32 * trainable // world
        gathered = (BF16 if mixed else FP32) * (sizes.unwrapped + 2 * sizes.largest_block)
        if sharding.offload:  # every process of the node keeps its shards in the same host memory
            host = (weights + gradients + optimizer) * world
            weights = gradients = optimizer = step = 0
        residual = BF16 if mixed else FP32
    elif sharding.kind in (SHARDING_ZERO2, SHARDING_ZERO3):
        weight_bytes = BF16 if mixed else FP32
        weights = weight_bytes * params // (world if sharding.kind == SHARDING_ZERO3 else 1)
        gradients = weight_bytes * trainable // world
        optimizer = (FP32 + ADAM_STATE_BYTES) * trainable // world  # fp32 master weights + moments
        step = FP32 * trainable // world
        if sharding.offload:
            host, optimizer, step = optimizer * world, 0, 0
        if sharding.kind == SHARDING_ZERO3:
            gathered = weight_bytes * (sizes.unwrapped + 2 * sizes.largest_block)
        residual = weight_bytes
    else:
        weights, gradients = FP32 * params, FP32 * trainable
        optimizer, step = ADAM_STATE_BYTES * trainable, FP32 * trainable
        autocast = BF16 * trainable if mixed else 0
        residual = FP32
    activations = activation_bytes(sizes, cfg.batch.per_device_batch_size, checkpointing, residual)
    return MemoryEstimate(weights, gradients, optimizer, step, autocast, gathered, activations, host)


def visible_gpu_bytes() -> list[int]:
    """Total memory of each visible CUDA device (empty without CUDA)."""
    if not torch.cuda.is_available():
        return []
    return [torch.cuda.mem_get_info(i)[1] for i in range(torch.cuda.device_count())]


def host_memory_bytes(cgroup_limit: str | Path = CGROUP_MEMORY_LIMIT) -> int:
    """The host's physical memory, or the container's cgroup limit when that is lower."""
    physical = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    try:
        limit = Path(cgroup_limit).read_text().strip()
    except OSError:
        return physical
    return min(physical, int(limit)) if limit.isdigit() else physical


def describe_run(cfg: TrainConfig, config_path: str | None = None) -> str:
    """`configs/train/x.yaml: llama2-7b, freeze_stage=full, precision=bf16, per-device batch 16`: the config
    file (when known) and the settings the estimate depends on."""
    settings = (
        f"{cfg.model.llm.type}, freeze_stage={cfg.freeze_stage}, precision={cfg.precision}, "
        f"per-device batch {cfg.batch.per_device_batch_size}"
    )
    return f"{config_path}: {settings}" if config_path else settings


def refuse_if_too_big(
    estimate: MemoryEstimate,
    sharding: Sharding,
    gpu_bytes: list[int],
    run: str,
    host_bytes: int | None = None,
) -> None:
    """`PreflightError` in one line when the estimate exceeds the smallest of `gpu_bytes`, or when what it
    offloads exceeds `HOST_MEMORY_USABLE` of `host_bytes`."""
    if host_bytes and estimate.host > HOST_MEMORY_USABLE * host_bytes:
        raise PreflightError(
            f"this run ({run}) keeps at least {estimate.host / GIB:.0f} GiB of model states in host memory with "
            f"{sharding.world_size} process(es) ({sharding.kind}, offload), more than "
            f"{HOST_MEMORY_USABLE:.0%} of the {host_bytes / GIB:.0f} GiB this machine has (the kernel would kill "
            "it without a message): spread it over more machines (configs/accelerate/fsdp_multinode.yaml), "
            "shard it over GPUs without offload (configs/accelerate/fsdp.yaml --num_processes N) or train LoRA "
            "(configs/train/openfly-7b-lora.yaml); docs/TRAINING.md, 'Memory'"
        )
    if not gpu_bytes or estimate.peak <= min(gpu_bytes):
        return
    raise PreflightError(
        f"this run ({run}) needs at least {estimate.peak / GIB:.0f} GiB per GPU with {sharding.world_size} "
        f"process(es) ({sharding.kind}{', offload' if sharding.offload else ''}), more than the "
        f"{min(gpu_bytes) / GIB:.0f} GiB this GPU has: launch more processes on more GPUs (accelerate launch "
        "--config_file configs/accelerate/fsdp.yaml --num_processes N), offload to host memory "
        "(configs/accelerate/fsdp_offload.yaml) or train LoRA (configs/train/openfly-7b-lora.yaml); "
        "docs/TRAINING.md, 'Memory'"
    )


def check_memory(cfg: TrainConfig, accelerator) -> MemoryEstimate | None:
    """On CUDA: log the run's per-GPU estimate in one line, and refuse (`PreflightError`) when it exceeds the
    smallest visible GPU or offloads more than the host can hold. Nothing is estimated on the CPU."""
    if accelerator.device.type != "cuda":
        return None
    sharding = sharding_of(accelerator)
    estimate = estimate_memory(model_sizes(cfg), cfg, sharding)
    logger.info(
        "memory estimate (%s, %d process(es)): %s", sharding.kind, sharding.world_size, estimate.summary()
    )
    run = describe_run(cfg, config_path_of(sys.argv[1:]))  # the --config_path train.py was given
    refuse_if_too_big(estimate, sharding, visible_gpu_bytes(), run, host_memory_bytes())
    return estimate
