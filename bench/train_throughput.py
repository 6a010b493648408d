"""Training throughput: samples/s, tokens/s and model FLOPs utilisation (MFU) of one optimizer step.

    python bench/train_throughput.py                  # tiny on CPU; 7B + LoRA + bf16 on CUDA when present
    python bench/train_throughput.py --configs tiny-cpu --batch 8 --steps 10
    python bench/train_throughput.py --configs 7b-lora-bf16 --levers none fused_adamw compile_layers
    python bench/train_throughput.py --configs tiny-cpu --profile outputs/profile.txt   # + torch.profiler table

Configurations (one JSON line each):
- `tiny-cpu`: the tiny preset (the `tiny-cnn` ResNet backbone), full fine-tune, fp32, on the CPU (the embedded
  default of train.py);
- `tiny-vit-cpu`: the same with `vision.type=tiny` (the two small ViTs at 112 px, the default before issue 12);
- `7b-lora-bf16`: the OpenFly-Agent 7B shape (random init) with LoRA r=32 on every LLM linear layer, the
  vision backbone frozen, bf16 autocast, gradient checkpointing (configs/train/openfly-7b-lora.yaml, 1 GPU).
Batches are synthetic but shaped like training: random 128 px frames resized by the agent's transform,
~90-token instructions, and every memory slot filled (K sets of S frames), the most expensive case.
FLOPs are model FLOPs as `train.py` logs them (`openfly_agent/training/throughput.py`: 2 N per token forward,
the backward that the trained parts need, attention, the vision backbone per encoded frame; activations that
gradient checkpointing recomputes are not counted). MFU divides them by the step time and the device's bf16
dense datasheet peak (`--peak_tflops` to override); on the CPU there is no peak, so `mfu` is null there.
`--levers` times the step once per speed lever, each alone on the same agent and batch: `none` (today's
defaults), `fused_adamw` (`optim.fused_adamw`, CUDA), `compile_layers` (`compile_layers`: torch.compile of each
decoder layer, compiled during the warm-up; timed last, it stays on). `--profile` writes torch.profiler's table
of a few more steps. Wall-clock figures depend on other load: `load_avg_1m` is reported with each CPU line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch

from openfly_agent import constants as C
from openfly_agent.data.collator import NavigationCollator
from openfly_agent.model.config import LoraSettings, TinyVitVisionConfig, make_model_config
from openfly_agent.model.freeze import freeze
from openfly_agent.model.language.lora import attach_lora
from openfly_agent.model.language.tokenizer import train_bpe_tokenizer
from openfly_agent.model.persistence.random_init import materialize_random_
from openfly_agent.training.metrics import count_llm_tokens
from openfly_agent.training.modes import compile_decoder_layers, enable_gradient_checkpointing
from openfly_agent.training.optim import make_optimizer
from openfly_agent.training.throughput import StepFlops, device_peak_flops, mfu
from openfly_agent.utils.profiling import write_profile

WORDS = [
    "fly",
    "forward",
    "to",
    "the",
    "red",
    "skyscraper",
    "with",
    "a",
    "rooftop",
    "billboard",
    "then",
    "turn",
    "left",
    "at",
    "the",
    "tower",
    "ascend",
    "above",
    "the",
    "white",
    "house",
    "and",
    "stop",
    "near",
    "the",
    "blue",
    "dome",
    "descend",
    "next",
    "to",
    "the",
    "grey",
    "tower",
    "go",
    "straight",
    "until",
    "the",
    "spire",
]
LEVERS = ("none", "fused_adamw", "compile_layers")  # in the order they are timed (compiling is not undone)


def instructions(count: int, words: int = 70, seed: int = 0) -> list[str]:
    """Template-like instructions of `words` words (about 90 BPE tokens, like the generated data)."""
    rng = np.random.default_rng(seed)
    return [" ".join(rng.choice(WORDS, size=words)) for _ in range(count)]


def build_agent(preset: str, device: str, vit: bool = False):
    """A randomly initialised agent of `preset` on `device` (7B: built on meta, materialised once there);
    `vit`: the tiny preset with the two small ViTs instead of the ResNet."""
    from openfly_agent.model.agent import OpenFlyAgent  # lazy: transformers

    tokenizer = train_bpe_tokenizer(instructions(64), vocab_size=1024)
    cfg = make_model_config(preset)
    if vit:
        cfg = dataclasses.replace(cfg, vision=TinyVitVisionConfig(image_size=112, patch_size=14))
    if cfg.llm.type == "tiny":
        return OpenFlyAgent.from_model_config(cfg, tokenizer=tokenizer).to(device)
    with torch.device("meta"):
        agent = OpenFlyAgent.from_model_config(cfg, tokenizer=tokenizer)
    materialize_random_(agent, device)
    agent.tokenizer = tokenizer
    return agent


def synthetic_batch(agent, batch: int, frame_px: int = 128, seed: int = 0) -> dict:
    """A collated training batch with every memory slot filled (K sets x S frames)."""
    cfg = agent.model_cfg
    k, s = cfg.memory.capacity, cfg.keyframes.set_size
    rng = np.random.default_rng(seed)

    def frame():
        return rng.integers(0, 256, (frame_px, frame_px, 3), dtype=np.uint8)

    def box():
        return np.array([0.5, 0.5, 0.6, 0.6], dtype=np.float32)

    samples = [
        {
            C.OBS_INSTRUCTION: text,
            C.OBS_RGB: frame(),
            C.MEMORY: [[(frame(), box(), True) for _ in range(s)] for _ in range(k)],
            C.ACTION: int(rng.integers(0, C.NUM_ACTIONS)),
            C.BOX: box(),
            C.BOX_VISIBLE: True,
        }
        for text in instructions(batch, seed=seed)
    ]
    collate = NavigationCollator(agent.processor, capacity=k, set_size=s)
    return collate(samples)


def time_steps(
    agent, batch: dict, steps: int, warmup: int, autocast, device: str, fused: bool = False, profile=None
) -> float:
    """Median seconds per optimizer step (forward, backward, clip, AdamW); `fused`: the fused AdamW kernel;
    `profile`: a path that gets torch.profiler's table of `steps` more steps."""
    optimizer = make_optimizer(agent, lr=1e-4, weight_decay=0.0, betas=(0.9, 0.95), fused=fused)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)

    def step() -> None:
        with autocast():
            loss, _ = agent(batch)
        loss.backward()
        torch.nn.utils.clip_grad_norm_([p for p in agent.parameters() if p.requires_grad], 1.0)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)

    times = []
    for i in range(warmup + steps):
        sync()
        start = time.perf_counter()
        step()
        sync()
        if i >= warmup:
            times.append(time.perf_counter() - start)
    if profile is not None:
        write_profile(step, profile, calls=steps, cuda=device == "cuda")
    return float(np.median(times))


def measure(
    name: str,
    batch_size: int,
    steps: int,
    warmup: int,
    peak_tflops: float | None,
    levers: tuple[str, ...] = ("none",),
    profile: str | None = None,
) -> list[dict]:
    """One configuration's JSON rows, one per lever (or one row saying why it was skipped)."""
    big = name.startswith("7b")
    row = {"config": name, "batch": batch_size}
    if big and not torch.cuda.is_available():
        return [{**row, "device": "cuda (absent)", "skipped": "needs CUDA (7B, bf16)"}]
    device = "cuda" if big else "cpu"
    torch.manual_seed(0)
    agent = build_agent("openfly-7b" if big else "tiny", device, vit=name == "tiny-vit-cpu").train()
    if big:
        attach_lora(agent, dataclasses.replace(LoraSettings(), rank=32, alpha=16))
        enable_gradient_checkpointing(agent)
        autocast = lambda: torch.autocast("cuda", dtype=torch.bfloat16)
    else:
        freeze(agent, "full")
        autocast = nullcontext
    batch = {
        k: v.to(device) if torch.is_tensor(v) else v for k, v in synthetic_batch(agent, batch_size).items()
    }
    flops = float(StepFlops.from_agent(agent).batch_flops(batch))
    tokens = count_llm_tokens(batch, agent.model_cfg)
    peak = device_peak_flops(device, peak_tflops)
    row.update(
        device=device,
        machine=torch.cuda.get_device_name(0) if big else f"{platform.processor() or platform.machine()} CPU",
        threads=torch.get_num_threads(),
        trainable_params=sum(p.numel() for p in agent.parameters() if p.requires_grad),
        params=sum(p.numel() for p in agent.parameters()),
        llm_tokens_per_sample=tokens / batch_size,
        model_tflop_per_step=round(flops / 1e12, 4),
        peak_tflops=round(peak / 1e12, 3) if peak else None,
        peak_source=None if peak is None else ("--peak_tflops" if peak_tflops else "bf16 datasheet"),
    )
    rows = []
    for lever in levers:
        try:
            if lever == "compile_layers":
                compile_decoder_layers(agent)
            if big:
                torch.cuda.reset_peak_memory_stats()
            seconds = time_steps(
                agent,
                batch,
                steps,
                warmup,
                autocast,
                device,
                lever == "fused_adamw",
                profile_path(profile, lever),
            )
        except Exception as err:  # a lever that fails on this machine is a row, not the end of the bench
            rows.append({**row, "lever": lever, "failed": f"{type(err).__name__}: {err}"})
            continue
        utilisation = mfu(flops, seconds, peak)
        result = {
            **row,
            "lever": lever,
            "step_s": round(seconds, 4),
            "samples_per_s": round(batch_size / seconds, 2),
            "tokens_per_s": round(tokens / seconds, 1),
            "model_tflops": round(flops / seconds / 1e12, 4),
            "mfu": round(utilisation, 4) if utilisation is not None else None,
        }
        if big:
            result["max_memory_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
        else:
            result["load_avg_1m"] = round(os.getloadavg()[0], 2)
        rows.append(result)
    return rows


def profile_path(profile: str | None, lever: str) -> str | None:
    """Where the profile of `lever` goes: `--profile` itself for `none`, else with the lever's name before the
    suffix (`profile-fused_adamw.txt`)."""
    if profile is None or lever == "none":
        return profile
    path = Path(profile)
    return str(path.with_name(f"{path.stem}-{lever}{path.suffix}"))


def build_parser() -> argparse.ArgumentParser:
    """The command line (tests/training/test_gpu_check.py parses the GPU check's commands with it)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", nargs="+", default=["tiny-cpu", "tiny-vit-cpu", "7b-lora-bf16"])
    parser.add_argument("--batch", type=int, default=8, help="samples per optimizer step (one micro-batch)")
    parser.add_argument("--steps", type=int, default=5, help="timed steps; step_s is their median")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--peak_tflops", type=float, default=None, help="GPU peak for MFU (bf16 dense)")
    parser.add_argument(
        "--levers", nargs="+", default=["none"], choices=LEVERS, help="one row per lever, each alone"
    )
    parser.add_argument(
        "--profile", default=None, help="write torch.profiler's table of --steps more steps here"
    )
    return parser


def main() -> None:
    args = build_parser().parse_args()
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    levers = tuple(lever for lever in LEVERS if lever in args.levers)  # compiling last: it is not undone
    for name in args.configs:
        for row in measure(name, args.batch, args.steps, args.warmup, args.peak_tflops, levers, args.profile):
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
