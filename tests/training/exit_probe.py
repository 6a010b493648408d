"""Run a script (train.py) as `__main__` and report, at exit, how its process group was torn down.

    python -m torch.distributed.run --standalone --nproc_per_node 2 tests/training/exit_probe.py train.py ...

Prints one line on stderr per process at exit: `exit-probe: rank=<r> destroy_calls=<n> ddp_alive=<k>
initialized=<bool>`, where `ddp_alive` is the number of DistributedDataParallel modules alive when the
process group was destroyed (it must be 0: a live DDP Reducer would hold the group's last reference and join
gloo's threads with the GIL held, the exit deadlock of issue 14).
"""

from __future__ import annotations

import atexit
import os
import runpy
import sys

import torch.distributed as dist

from openfly_agent.utils.distributed import live_ddp_modules

_alive_at_destroy: list[int] = []
_destroy = dist.destroy_process_group


def _recording_destroy(group=None):
    _alive_at_destroy.append(live_ddp_modules())
    return _destroy(group)


def _report() -> None:
    alive = max(_alive_at_destroy, default=-1)
    line = (
        f"exit-probe: rank={os.environ.get('RANK', '0')} destroy_calls={len(_alive_at_destroy)} "
        f"ddp_alive={alive} initialized={dist.is_initialized()}\n"
    )
    # one write(2) of the whole line: the two ranks share stderr, and print's separate writes of the text and
    # its newline interleaved ("initialized=Falseexit-probe: rank=1 ...") in a CI run
    sys.stderr.flush()
    os.write(sys.stderr.fileno(), line.encode())


dist.destroy_process_group = _recording_destroy
atexit.register(_report)
script, sys.argv = sys.argv[1], sys.argv[1:]
runpy.run_path(script, run_name="__main__")
