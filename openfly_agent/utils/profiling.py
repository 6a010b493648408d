"""torch.profiler around a few calls of a function, written as its table of the most expensive operators (the
`--profile` option of `bench/train_throughput.py` and `bench/step_latency.py`)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch


def write_profile(
    fn: Callable[[], object], path: str | Path, calls: int = 1, cuda: bool = False, top_k: int = 30
):
    """Run `fn` `calls` times under torch.profiler and write the `top_k` operators, sorted by their own CUDA time
    (`cuda`, the GPU's kernels) or their own CPU time, to `path` (its folder is created). Returns the path."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities, record_shapes=False) as prof:
        for _ in range(calls):
            fn()
        if cuda:
            torch.cuda.synchronize()
    sort_by = "self_cuda_time_total" if cuda else "self_cpu_time_total"
    table = prof.key_averages().table(sort_by=sort_by, row_limit=top_k)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"# {calls} call(s), sorted by {sort_by}\n{table}\n")
    return path
