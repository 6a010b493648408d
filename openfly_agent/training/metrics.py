"""Throughput, token counts, memory and running means for the training log."""

from __future__ import annotations

import resource
import sys
import time
from collections import defaultdict

import torch

from openfly_agent.training.throughput import llm_row_tokens


class ThroughputMeter:
    """Samples/s and tokens/s between two `report` calls (wall clock; counts summed over processes)."""

    def __init__(self) -> None:
        self._start = time.perf_counter()
        self._samples = 0
        self._tokens = 0

    def update(self, samples: int, tokens: int) -> None:
        """Count one micro-batch of this process."""
        self._samples += samples
        self._tokens += tokens

    def report(self, accelerator=None) -> dict[str, float]:
        """Rates since the previous report (or the start), summed over processes, then reset.

        With an `accelerator`, every process must call this at the same step (it all-reduces the counts).
        """
        elapsed = max(time.perf_counter() - self._start, 1e-9)
        counts = torch.tensor([self._samples, self._tokens], dtype=torch.float64)
        if accelerator is not None and accelerator.num_processes > 1:
            counts = accelerator.reduce(counts.to(accelerator.device), reduction="sum").cpu()
        rates = {"samples_per_s": float(counts[0]) / elapsed, "tokens_per_s": float(counts[1]) / elapsed}
        self.__init__()
        return rates


def memory_stats(device: torch.device) -> dict[str, float]:
    """Peak accelerator memory (CUDA) or peak resident memory of this process (CPU), in GiB."""
    if device.type == "cuda":
        return {
            "memory_allocated_gib": torch.cuda.max_memory_allocated(device) / 2**30,
            "memory_reserved_gib": torch.cuda.max_memory_reserved(device) / 2**30,
        }
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    scale = 2**30 if sys.platform == "darwin" else 2**20
    return {"memory_rss_peak_gib": peak / scale}


class RunningMeans:
    """Weighted means of logged floats over micro-batches, steps and (with `reduce`) processes.

    `box_iou` is a mean over the visible boxes of its micro-batch, so it is weighted by `num_visible_boxes`;
    everything else counts once per micro-batch. NaN values add nothing. Keys are never dropped, so every
    process reduces the same vector.
    """

    WEIGHTS = {"box_iou": "num_visible_boxes"}

    def __init__(self) -> None:
        self._sums: dict[str, float] = defaultdict(float)
        self._counts: dict[str, float] = defaultdict(float)

    def add(self, values: dict[str, float]) -> None:
        """Add one micro-batch's logs."""
        for key, value in values.items():
            value = float(value)
            weight = float(values.get(self.WEIGHTS[key], 1.0)) if key in self.WEIGHTS else 1.0
            if value != value:  # NaN
                value, weight = 0.0, 0.0
            self._sums[key] += value * weight
            self._counts[key] += weight

    def pop(self, accelerator=None) -> dict[str, float]:
        """The means so far (summed over processes when an `accelerator` is given), then reset.

        With an `accelerator`, every process must call this at the same step (it all-reduces).
        """
        keys = sorted(self._sums)
        totals = torch.tensor(
            [[self._sums[k] for k in keys], [self._counts[k] for k in keys]], dtype=torch.float64
        )
        if accelerator is not None and accelerator.num_processes > 1:
            totals = accelerator.reduce(totals.to(accelerator.device), reduction="sum").cpu()
        self.__init__()
        return {k: float(s / c) if c > 0 else float("nan") for k, s, c in zip(keys, *totals.tolist())}


def count_llm_tokens(batch: dict, model_cfg) -> int:
    """LLM sequence positions of a batch, summed over its rows (`throughput.llm_row_tokens`)."""
    return int(llm_row_tokens(batch, model_cfg).sum())
