"""Visual tokens per step and milliseconds per `select_action` call, keyframe memory vs uniform history.

    python bench/step_latency.py                      # tiny on CPU; 7B on CUDA when present
    python bench/step_latency.py --presets tiny --batches 1 16 --steps 20
    python bench/step_latency.py --presets tiny --histories keyframe --profile outputs/select_action.txt

Configurations (one JSON line each):
- history `keyframe`: the model as configured: the current frame's P tokens + K memory sets pooled to
  (sqrt(P) / g)^2 tokens each (256 + 2 = 258 for the 7B preset);
- history `uniform`: the baseline with K full frames of history (g = 1, no merging): P + K * P tokens.
Every episode's memory is filled with K sets before timing, so each step carries the full history.
The 7B preset (random init, bf16) needs CUDA; elsewhere its line has the token count and `ms_per_step: null`.
On CUDA each line has the peak memory allocated during its calls, weights included (`max_memory_gib`). `--profile PATH`
writes torch.profiler's table of one more `select_action` call per line (`PATH` with `-<preset>-<history>-b<batch>`
before its suffix).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

from openfly_agent.model.config import MemoryConfig, MergingConfig, ModelConfig, make_model_config
from openfly_agent.model.language.tokenizer import train_bpe_tokenizer
from openfly_agent.model.persistence.random_init import materialize_random_
from openfly_agent.utils.profiling import write_profile

HISTORIES = ("keyframe", "uniform")
INSTRUCTIONS = [
    "Fly forward to the red skyscraper with a rooftop billboard, then turn left at the tower.",
    "Ascend above the white house and stop near the blue dome on the right.",
    "Turn right after the park and go straight until you reach the tall spire.",
]


def history_variant(cfg: ModelConfig, history: str) -> ModelConfig:
    """The configured keyframe memory, or the uniform baseline with K full-resolution frames."""
    if history == "keyframe":
        return cfg
    return dataclasses.replace(
        cfg, memory=MemoryConfig(capacity=cfg.memory.capacity, grid=1), merging=MergingConfig(enabled=False)
    )


def build_agent(cfg: ModelConfig, device: str, dtype: torch.dtype):
    """A randomly initialised agent on `device` (7B: created on meta, materialised once, init there)."""
    from openfly_agent.model.agent import OpenFlyAgent  # lazy: transformers

    tokenizer = train_bpe_tokenizer(INSTRUCTIONS * 8, vocab_size=512)
    if cfg.llm.type == "tiny":
        return OpenFlyAgent.from_model_config(cfg, tokenizer=tokenizer).to(device=device, dtype=dtype).eval()
    with torch.device("meta"):
        agent = OpenFlyAgent.from_model_config(cfg)
    materialize_random_(agent, device, dtype)
    agent.tokenizer = tokenizer  # prompt length stand-in for the Llama tokenizer (same order of tokens)
    return agent.eval()


def fill_memory(session, episode_ids: list[str]) -> None:
    """Push K keyframe sets (tokens of random frames through the real merge / pool / projector path) into the
    memories of the agent session's episodes."""
    network = session.agent.network
    cfg = network.cfg
    device = network.projector.fc1.weight.device
    for episode_id in episode_ids:
        state = session.episodes[episode_id]
        for k in range(cfg.memory.capacity):
            s = cfg.keyframes.set_size
            pixels = torch.randint(
                0, 256, (s, 3, cfg.vision.image_size, cfg.vision.image_size), dtype=torch.uint8
            )
            with torch.no_grad():
                features = network.vision_backbone(pixels.to(device))[None]  # (1, S, P, D_v)
                mask = torch.ones(1, s, dtype=torch.bool, device=device)
                boxes = torch.full((1, s, 4), 0.5, device=device)
                tokens = network.memory.set_tokens(network.projector, features, mask, boxes, mask)[0]
                state.memory.bank.push(("bench", k), tokens)


def time_steps(agent, batch: int, steps: int, warmup: int, profile: str | None = None) -> tuple[float, float]:
    """Median and mean milliseconds per `select_action` over `steps` calls with a full memory (`profile`: a
    path that gets torch.profiler's table of one more call)."""
    size = agent.model_cfg.vision.image_size
    rng = np.random.default_rng(0)
    ids = [f"ep{i}" for i in range(batch)]

    def observations():
        frames = rng.integers(0, 256, (batch, size, size, 3), np.uint8)
        return [
            {"episode_id": e, "instruction": INSTRUCTIONS[i % len(INSTRUCTIONS)], "rgb": frames[i]}
            for i, e in enumerate(ids)
        ]

    session = agent.new_session()
    session.select_action(observations())
    fill_memory(session, ids)
    for _ in range(warmup):
        session.select_action(observations())
    sync = torch.cuda.synchronize if agent.network.projector.fc1.weight.is_cuda else (lambda: None)
    times = []
    for _ in range(steps):
        obs = observations()
        sync()
        start = time.perf_counter()
        session.select_action(obs)
        sync()
        times.append(1000.0 * (time.perf_counter() - start))
    for i in ids:  # memory must still be full (K sets) for the numbers to mean what they say
        assert len(session.episodes[i].memory) == agent.model_cfg.memory.capacity
    if profile is not None:
        obs = observations()
        write_profile(
            lambda: session.select_action(obs), profile, cuda=agent.network.projector.fc1.weight.is_cuda
        )
    return float(np.median(times)), float(np.mean(times))


def run(
    presets: list[str],
    batches: list[int],
    steps: int,
    warmup: int,
    histories: tuple[str, ...] = HISTORIES,
    profile: str | None = None,
) -> None:
    """Print one JSON line per (preset, history, batch)."""
    cuda = torch.cuda.is_available()
    cpu_name = f"{platform.processor() or platform.machine()} CPU"
    for preset in presets:
        big = preset != "tiny"
        device = "cuda" if big else "cpu"  # the tiny preset is the CPU configuration
        dtype = torch.bfloat16 if big else torch.float32
        for history in histories:
            cfg = history_variant(make_model_config(preset), history)
            agent = build_agent(cfg, device, dtype) if (not big or cuda) else None
            for batch in batches:
                row = {
                    "preset": preset,
                    "history": history,
                    "device": device if agent is not None else "cuda (absent)",
                    "dtype": str(dtype).removeprefix("torch."),
                    "batch": batch,
                    "visual_tokens_per_step": cfg.visual_tokens_per_step(),
                    "ms_per_step": None,
                    "machine": torch.cuda.get_device_name(0) if device == "cuda" and cuda else cpu_name,
                    "threads": torch.get_num_threads(),
                }
                if agent is not None:
                    path = None
                    if profile is not None:
                        path = Path(profile).with_name(
                            f"{Path(profile).stem}-{preset}-{history}-b{batch}.txt"
                        )
                    if device == "cuda":
                        torch.cuda.reset_peak_memory_stats()
                    median, mean = time_steps(agent, batch, steps, warmup, path)
                    row.update(ms_per_step=round(median, 2), ms_mean=round(mean, 2), steps=steps)
                    row["load_avg_1m"] = round(os.getloadavg()[0], 2)  # other processes sharing the CPU
                    if device == "cuda":
                        row["max_memory_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
                else:
                    row["skipped"] = "needs CUDA (7B in bf16)"
                print(json.dumps(row), flush=True)
            del agent


def build_parser() -> argparse.ArgumentParser:
    """The command line (tests/training/test_gpu_check.py parses the GPU check's commands with it)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["tiny", "openfly-7b"])
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 16])
    parser.add_argument("--steps", type=int, default=20, help="timed calls; ms_per_step is their median")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--histories", nargs="+", default=list(HISTORIES), choices=HISTORIES)
    parser.add_argument(
        "--profile", default=None, help="write torch.profiler's table of one call per line here"
    )
    return parser


def main() -> None:
    args = build_parser().parse_args()
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    torch.manual_seed(0)
    run(args.presets, args.batches, args.steps, args.warmup, tuple(args.histories), args.profile)


if __name__ == "__main__":
    main()
