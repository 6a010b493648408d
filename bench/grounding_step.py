"""Milliseconds of one grounding-stage micro-step (forward, backward, AdamW) on the stage's real batches.

    python bench/grounding_step.py                                   # the recipe's grounding stage, one thread
    python bench/grounding_step.py -- --model.llm.length_groups=2    # any train.py override after --
    python bench/grounding_step.py --steps 40 -- --precision=bf16 --model.llm.attn_implementation=eager
    python bench/grounding_step.py -- --stage=navigation             # a navigation-stage micro-step instead

Builds the agent and the micro-batches exactly as `train.py --stage=grounding` does (configs/train/tiny.yaml, the
recipe's grounding options, then the overrides), one process, `--threads` torch threads (1: as each of the
recipe's two processes). Prints one JSON line: the median ms per micro-step over `steps` batches after `warmup`,
and the prompt and frame tokens the LLM reads per micro-batch, padded (rows x longest) and attended.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from contextlib import nullcontext

import torch

from openfly_agent import constants as C
from openfly_agent.model.layout import last_true_index
from openfly_agent.training.accelerator import make_accelerator
from openfly_agent.training.builder import load_splits, prepare_agent
from openfly_agent.training.cli import parse_args
from openfly_agent.training.loaders import make_train_loader
from openfly_agent.training.optim import make_optimizer
from openfly_agent.training.preflight import resolve_val_split
from openfly_agent.training.stages import stage_data

# the shipped recipe's grounding stage (configs/recipe/tiny-recipe.yaml) on the embedded-small datasets
STAGE_ARGS = [
    "--config_path=configs/train/tiny.yaml",
    "--data.root=outputs/datasets/embedded-small",
    "--data.grounding_root=outputs/datasets/grounding-small",
    "--stage=grounding",
    "--model.grounding.attribute_weight=1.0",
    "--model.vision.cnn_colour_stats=true",
    "--output_dir=outputs/bench/grounding_step",
    "--resume=false",
    "--logging.tracker=none",
]


def build(overrides: list[str]):
    """(agent, train dataset, collate, cfg) of a grounding-stage run of `STAGE_ARGS + overrides`."""

    cfg = parse_args(STAGE_ARGS + overrides)
    cfg = dataclasses.replace(cfg, data=resolve_val_split(cfg.data)[0])  # as train() does first
    splits = load_splits(cfg.data, cfg.model.grounding)
    agent = prepare_agent(cfg, splits, make_accelerator(cfg), None)
    data = stage_data(cfg, splits, agent)
    return agent, data.train, data.collate, cfg


def main(argv: list[str] | None = None) -> dict:
    argv = sys.argv[1:] if argv is None else argv
    ours, overrides = (argv[: argv.index("--")], argv[argv.index("--") + 1 :]) if "--" in argv else (argv, [])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(ours)
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        record = measure(args, overrides)
    finally:
        torch.set_num_threads(threads)  # a caller in the same process (a test) keeps its own
    print(json.dumps(record))
    return record


def measure(args: argparse.Namespace, overrides: list[str]) -> dict:

    agent, train_set, collate, cfg = build(overrides)
    loader, _ = make_train_loader(train_set, collate, cfg)
    batches = []
    for batch in loader:
        batches.append(batch)
        if len(batches) == args.warmup + args.steps:
            break
    optim = cfg.optim
    optimizer = make_optimizer(agent, optim.lr, optim.weight_decay, optim.betas, optim.eps)
    precision = {"bf16": torch.bfloat16, "fp16": torch.float16}.get(cfg.precision)
    autocast = (lambda: torch.autocast("cpu", dtype=precision)) if precision else nullcontext
    agent.train()
    times, padded, attended = [], [], []
    for step, batch in enumerate(batches):
        start = time.perf_counter()
        with autocast():
            loss, _ = agent(batch)
        loss.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        if step >= args.warmup:
            times.append(1000 * (time.perf_counter() - start))
            mask = batch[C.ATTENTION_MASK].bool()  # (B, L) text; every row also has the frame's tokens
            visual = cfg.model.vision.num_patches
            padded.append(mask.shape[0] * (mask.shape[1] + visual))
            attended.append(int((last_true_index(mask) + 1 + visual).sum()))
    return {
        "overrides": overrides,
        "threads": args.threads,
        "micro_batch_rows": int(batches[0][C.INPUT_IDS].shape[0]),
        "ms_per_micro_step": round(statistics.median(times), 1),
        "padded_tokens": round(statistics.mean(padded)),
        "attended_tokens": round(statistics.mean(attended)),
    }


if __name__ == "__main__":
    main()
