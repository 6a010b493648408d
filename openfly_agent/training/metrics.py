"""Throughput, memory and running means for the training log; box IoU for validation."""

from __future__ import annotations

import resource
import sys
import time
from collections import defaultdict

import torch


class ThroughputMeter:
    """Samples/s and tokens/s between two `report` calls (wall clock, all processes' samples counted)."""

    def __init__(self) -> None:
        self._start = time.perf_counter()
        self._samples = 0
        self._tokens = 0

    def update(self, samples: int, tokens: int) -> None:
        """Count one optimizer step's global batch."""
        self._samples += samples
        self._tokens += tokens

    def report(self) -> dict[str, float]:
        """Rates since the previous report (or the start), then reset."""
        elapsed = max(time.perf_counter() - self._start, 1e-9)
        rates = {"samples_per_s": self._samples / elapsed, "tokens_per_s": self._tokens / elapsed}
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
    """Means of logged floats accumulated over micro-batches and steps, emptied by `pop`."""

    def __init__(self) -> None:
        self._sums: dict[str, float] = defaultdict(float)
        self._counts: dict[str, int] = defaultdict(int)

    def add(self, values: dict[str, float]) -> None:
        """Add one micro-batch's logs (NaN values, e.g. an IoU with no visible box, are skipped)."""
        for key, value in values.items():
            value = float(value)
            if value == value:  # not NaN
                self._sums[key] += value
                self._counts[key] += 1

    def pop(self) -> dict[str, float]:
        """The means so far, then reset."""
        means = {k: self._sums[k] / self._counts[k] for k in self._sums}
        self.__init__()
        return means


def box_iou_cxcywh(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """IoU of matching boxes given as (cx, cy, w, h) in [0, 1]: (N, 4), (N, 4) -> (N,)."""
    p_lo, p_hi = pred[:, :2] - pred[:, 2:] / 2, pred[:, :2] + pred[:, 2:] / 2  # (N, 2) each
    t_lo, t_hi = target[:, :2] - target[:, 2:] / 2, target[:, :2] + target[:, 2:] / 2
    inter = (torch.minimum(p_hi, t_hi) - torch.maximum(p_lo, t_lo)).clamp(min=0).prod(dim=1)  # (N,)
    union = pred[:, 2:].prod(dim=1) + target[:, 2:].prod(dim=1) - inter
    return inter / union.clamp(min=1e-12)
