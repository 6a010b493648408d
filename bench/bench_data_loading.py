"""Data-loading figures: PNG decode, writer throughput, dataset sample time (cold / warm cache), collate.

    PYTHONPATH=. python bench/bench_data_loading.py [--size 224] [--episodes 20] [--steps 30]

Prints one JSON line per figure. Frames are smooth synthetic images (gradients and blocks) so PNG sizes
are closer to rendered frames than random noise would be.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from openfly_agent.data.collator import NavigationCollator
from openfly_agent.data.dataset import NavigationStepDataset
from openfly_agent.data.frames import FrameStore, decode_image, encode_image
from openfly_agent.data.schema import Episode
from openfly_agent.data.writer import OpenFlyDatasetWriter
from openfly_agent.model.language.action_tokenizer import ActionTokenizer
from openfly_agent.model.language.tokenizer import train_bpe_tokenizer


def synthetic_frame(size: int, rng: np.random.Generator) -> np.ndarray:
    y, x = np.mgrid[0:size, 0:size]
    rgb = np.stack([x * 255 // size, y * 255 // size, (x + y) * 127 // size], axis=-1).astype(np.uint8)
    for _ in range(12):
        x0, y0, w, h = rng.integers(0, size, 4)
        rgb[y0 : y0 + h // 3, x0 : x0 + w // 3] = rng.integers(0, 256, 3)
    return rgb


def make_episode(i: int, steps: int) -> Episode:
    rng = np.random.default_rng(i)
    actions = np.concatenate([rng.choice([1, 2, 3, 8, 9], steps - 1), [0]])
    visible = rng.random(steps) < 0.7
    boxes = np.where(visible[:, None], [0.5, 0.5, 0.4, 0.4], 0.0)
    return Episode(
        episode_id=f"embedded-0/astar_data/low_short/traj_{i:04d}",
        scene_id="embedded-0",
        instruction="fly to the red tower and stop on its left",
        actions=actions,
        positions=np.zeros((steps, 3)),
        yaws=np.zeros(steps),
        frame_ids=[f"20250101_000000_{t}" for t in range(steps)],
        split="train",
        category="low_short",
        boxes=boxes,
        box_visible=visible,
    )


class EveryChangeSelector:
    """Stand-in for model.keyframes: sets of 5 frames around the last two action changes."""

    def select(self, actions, box_areas, t):
        changes = [c for c in range(1, t) if actions[c] != actions[c - 1] and c + 2 <= t - 1]
        return [list(range(max(0, c - 2), c + 3)) for c in changes[-2:]]


def make_processor(texts: list[str]):
    """The model's input processor at 224 px (the 7B input size), with a BPE tokenizer trained on `texts`."""
    from openfly_agent.model.processor import OpenFlyProcessor  # lazy: transformers

    tokenizer = train_bpe_tokenizer(texts, vocab_size=512)
    actions = ActionTokenizer(vocab_end=len(tokenizer) + 256)
    return OpenFlyProcessor(tokenizer, image_size=224, action_head=actions.to_dict())


def machine() -> str:
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        cpu = next(line.split(":", 1)[1].strip() for line in lines if line.startswith("model name"))
    except (OSError, StopIteration):
        cpu = platform.machine()
    return f"{cpu}, {os.cpu_count()} cores"


def emit(name: str, **values) -> None:
    print(json.dumps({"bench": name, "machine": machine(), **values}))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--size", type=int, default=224)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--steps", type=int, default=30)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    frame = synthetic_frame(args.size, rng)
    png = encode_image(frame)
    start = time.perf_counter()
    for _ in range(200):
        decode_image(png, "bench", 0)
    emit(
        "png_decode",
        size=args.size,
        png_kb=round(len(png) / 1024, 1),
        ms=round((time.perf_counter() - start) * 5, 3),
    )

    with tempfile.TemporaryDirectory() as root:
        writer = OpenFlyDatasetWriter(root)
        episodes = [make_episode(i, args.steps) for i in range(args.episodes)]
        frames = [[synthetic_frame(args.size, rng) for _ in range(args.steps)] for _ in episodes]
        start = time.perf_counter()
        for episode, episode_frames in zip(episodes, frames):
            writer.write_episode(episode, episode_frames)
        elapsed = time.perf_counter() - start
        emit("writer", frames_per_s=round(args.episodes * args.steps / elapsed, 1))
        start = time.perf_counter()
        writer.finalize()
        emit("finalize", episodes=args.episodes, s=round(time.perf_counter() - start, 3))

        for history in ("none", "keyframes"):
            store = FrameStore(root, cache_episodes=args.episodes, cache_frames=args.episodes * args.steps)
            dataset = NavigationStepDataset(
                episodes, store, history, capacity=2, set_size=5, keyframe_selector=EveryChangeSelector()
            )
            for label in ("cold", "warm"):
                start = time.perf_counter()
                samples = [dataset[i] for i in range(len(dataset))]
                ms = (time.perf_counter() - start) / len(dataset) * 1000
                frames_per_sample = np.mean([1 + sum(len(s) for s in x["memory"]) for x in samples])
                emit(
                    "sample",
                    history=history,
                    cache=label,
                    ms=round(ms, 3),
                    frames=round(frames_per_sample, 2),
                )
        collator = NavigationCollator(
            make_processor([e.instruction for e in episodes]), capacity=2, set_size=5
        )
        start = time.perf_counter()
        for i in range(0, 64, 16):
            collator(samples[i : i + 16])
        emit("collate", batch=16, ms=round((time.perf_counter() - start) / 4 * 1000, 2))


if __name__ == "__main__":
    main()
