"""Ending a multi-process run (gloo / NCCL through accelerate or torchrun) without a hang at exit.

The default process group must be destroyed on every rank, after the last collective, while the interpreter
is fully alive, and its last reference must be dropped through the Python `ProcessGroup` object: that holder
releases the GIL while the C++ destructor joins the backend's worker threads. Dropped anywhere else (DDP's
C++ `Reducer` is the usual last holder when `destroy_process_group()` runs while the model is still alive),
the destructor joins those threads with the GIL held; a gloo worker still releasing the tensors of its last
collective needs the GIL to do so, and the rank deadlocks (issue 14: one rank of a two-process run stuck in
a futex wait after training had finished).
"""

from __future__ import annotations

import gc
import logging

logger = logging.getLogger(__name__)


def live_ddp_modules() -> int:
    """How many `DistributedDataParallel` wrappers are alive (their C++ Reducer holds the process group)."""
    from torch.nn.parallel import DistributedDataParallel

    return sum(isinstance(obj, DistributedDataParallel) for obj in gc.get_objects())


def close_process_group(synchronize: bool = True) -> None:
    """Destroy the default process group, if any, in the order that cannot deadlock.

    Call it last, once the objects built on the group (prepared models, optimizers, loaders) are released.

    Args:
        synchronize: barrier first, so no rank tears its side down while another is still in a collective.
            Pass False on error paths: a rank that failed must not wait for ranks that may never arrive.
    """
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()):
        return
    gc.collect()  # wrappers in reference cycles die now, while the group is still registered
    leftover = live_ddp_modules()
    if leftover:
        logger.warning(
            "%d DistributedDataParallel module(s) still alive while the process group closes", leftover
        )
    if synchronize:
        dist.barrier()
    group = dist.group.WORLD  # keeps the group alive through destroy_process_group() ...
    dist.destroy_process_group()
    del group  # ... so this is its last reference: the destructor runs with the GIL released
