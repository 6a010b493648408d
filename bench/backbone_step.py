"""Milliseconds of one forward + backward of the tiny-cnn vision backbone, by stem (`vision.cnn_stem`).

    python bench/backbone_step.py --stem resnet
    python bench/backbone_step.py --stem patch4 --batch 8 --steps 60 --image_size 128

The backbone alone, as one training process runs it (one thread by default, as the recipe's two processes):
random uint8 frames, the colour path on as the recipe trains, the sum of the tokens as the loss. Prints one JSON
line (median ms over `steps` after `warmup`).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from openfly_agent.model.config import CNN_STEMS, TinyCnnVisionConfig
from openfly_agent.model.vision.conv import ConvVisionBackbone


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stem", choices=CNN_STEMS, default="resnet")
    parser.add_argument("--batch", type=int, default=8, help="frames per step (a process's micro-batch)")
    parser.add_argument("--image_size", type=int, default=128)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    backbone = ConvVisionBackbone(
        TinyCnnVisionConfig(image_size=args.image_size, cnn_stem=args.stem, cnn_colour_stats=True)
    ).train()
    pixels = torch.randint(0, 256, (args.batch, 3, args.image_size, args.image_size), dtype=torch.uint8)
    times = []
    for step in range(args.warmup + args.steps):
        start = time.perf_counter()
        backbone(pixels).sum().backward()  # (F, P, C) tokens
        if step >= args.warmup:
            times.append(1000 * (time.perf_counter() - start))
    record = {
        "stem": args.stem,
        "batch": args.batch,
        "image_size": args.image_size,
        "threads": args.threads,
        "parameters": sum(p.numel() for p in backbone.parameters()),
        "ms_per_step": round(statistics.median(times), 2),
    }
    print(json.dumps(record))


if __name__ == "__main__":
    main()
