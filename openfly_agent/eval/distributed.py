"""Splitting evaluation over processes (`accelerate launch` / `torchrun`): shards, per-rank logs, merging.

Each rank takes a deterministic shard of the episodes and appends to its own log
(`episodes.rank<k>.jsonl`); after a barrier, rank 0 merges every log of the folder into
`episodes.jsonl` and writes the reports. A single process writes `episodes.jsonl` directly.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from openfly_agent import constants as C
from openfly_agent.eval.records import merge_records, read_jsonl, write_jsonl_atomic
from openfly_agent.rollout.record import EpisodeRecord

T = TypeVar("T")
_RANK_LOG = re.compile(r"^episodes\.rank(\d+)\.jsonl$")


@dataclass
class ProcessInfo:
    """This process' place in the run; `state` is accelerate's `PartialState` (None when not created)."""

    rank: int = 0
    world_size: int = 1
    state: object | None = None

    @property
    def is_main(self) -> bool:
        """Rank 0: the process that merges logs and writes reports."""
        return self.rank == 0

    def wait(self) -> None:
        """Barrier across processes (no-op for a single process)."""
        if self.world_size > 1 and self.state is not None:
            self.state.wait_for_everyone()


def process_info(cpu: bool | None = None) -> ProcessInfo:
    """Rank and world size from accelerate (initialises the process group under a launcher).

    Args:
        cpu: processes run on the CPU; None = when CUDA is absent. accelerate forms a multi-process CPU group
            (gloo) only when asked for the CPU: without it, `accelerate launch --multi_gpu` or torchrun on a
            CPU machine would start processes that each believe they are alone.
    """
    import torch
    from accelerate import PartialState

    if cpu is None:
        cpu = not torch.cuda.is_available()
    state = PartialState(cpu=cpu)
    return ProcessInfo(rank=int(state.process_index), world_size=int(state.num_processes), state=state)


def shard(items: list[T], rank: int, world_size: int) -> list[T]:
    """Every `world_size`-th item starting at `rank` (round robin keeps long and short episodes mixed)."""
    if not 0 <= rank < world_size:
        raise ValueError(f"rank {rank} is outside a world of {world_size} processes")
    return items[rank::world_size]


def log_name(info: ProcessInfo) -> str:
    """The log this process appends to."""
    return C.EPISODES_JSONL if info.world_size == 1 else f"episodes.rank{info.rank}.jsonl"


def log_files(folder: str | Path) -> list[Path]:
    """Every episode log of `folder`: the merged `episodes.jsonl` first, then the rank logs by rank."""
    folder = Path(folder)
    ranked = sorted(
        (int(m.group(1)), p) for p in folder.glob("episodes.rank*.jsonl") if (m := _RANK_LOG.match(p.name))
    )
    merged = folder / C.EPISODES_JSONL
    return ([merged] if merged.is_file() else []) + [p for _, p in ranked]


def read_all_logs(folder: str | Path) -> list[EpisodeRecord]:
    """The union of every log of `folder`, one record per (split, episode id), sorted."""
    return merge_records([read_jsonl(p) for p in log_files(folder)])


def merge_logs(folder: str | Path) -> list[EpisodeRecord]:
    """Rank 0, after the barrier: fold the rank logs into `episodes.jsonl` (atomic) and delete them; a log
    that holds retried episodes is rewritten with one record per episode (the retry replaces the error)."""
    folder = Path(folder)
    files = log_files(folder)
    logs = [read_jsonl(p) for p in files]
    records = merge_records(logs)
    rank_logs = [p for p in files if p.name != C.EPISODES_JSONL]
    if rank_logs or sum(map(len, logs)) != len(records):
        write_jsonl_atomic(folder / C.EPISODES_JSONL, records)
        for path in rank_logs:
            path.unlink()
    return records
