"""Child processes that never outlive their caller: on timeout the whole tree is killed, launcher and workers.

    done = run_group([sys.executable, "train.py", ...], timeout=300)    # CompletedProcess, or GroupTimeout
    with running([sys.executable, "eval.py", ...]) as proc: ...         # stopped on leaving the block

`subprocess.run(..., timeout=...)` kills only the direct child. A launcher's workers survive that: torchrun
even starts each worker in a session of its own, so killing the launcher's process group misses them too,
and a hung worker is left running, orphaned (issue 14). Here the child starts a new session, and stopping it
signals every process group of its descendants (found through /proc before anything is killed). Used by the
tests and scripts that start processes. Linux only (/proc); elsewhere only the child's group is signalled.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
from collections.abc import Iterator, Sequence
from pathlib import Path

KILL_GRACE_S = 5.0  # after SIGTERM, seconds before SIGKILL


class GroupTimeout(subprocess.TimeoutExpired):
    """A process tree ran past its timeout and was killed; `output` / `stderr` hold what it printed."""


def start_group(command: Sequence[str], **popen_kwargs) -> subprocess.Popen:
    """`subprocess.Popen(command)` in a new session (its own process group)."""
    return subprocess.Popen(list(command), start_new_session=True, **popen_kwargs)


def _stat(pid: int | str) -> list[str] | None:
    """Fields of /proc/<pid>/stat after the command name (state, ppid, pgrp, ...), or None."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def _start_time(pid: int) -> str | None:
    """When `pid` started (clock ticks since boot), to tell it from a later process that reuses the number."""
    fields = _stat(pid)
    return fields[19] if fields and len(fields) > 19 else None


def descendants(pid: int) -> list[int]:
    """Every process below `pid` (children, their children, ...); Linux /proc, empty elsewhere."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").glob("[0-9]*"):
        fields = _stat(entry.name)
        if fields:
            children.setdefault(int(fields[1]), []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def tree_of(proc: subprocess.Popen) -> dict[int, str | None]:
    """{pid: start time} of `proc` and every process below it, found now (a launcher's workers lose that link
    once it dies, so the tree is taken before anything is signalled)."""
    return {pid: _start_time(pid) for pid in [proc.pid, *descendants(proc.pid)]}


def kill_tree(
    proc: subprocess.Popen, sig: int = signal.SIGKILL, tree: dict[int, str | None] | None = None
) -> None:
    """Send `sig` to every process of `tree` (default: `proc`'s tree now) that is still the same process, and
    to their process groups."""
    tree = tree_of(proc) if tree is None else tree
    alive = [pid for pid, start in tree.items() if start is not None and _start_time(pid) == start]
    groups = set()
    for pid in alive:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            groups.add(os.getpgid(pid))
    for group in groups - {os.getpgrp()}:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(group, sig)
    for pid in alive:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, sig)


def stop_group(proc: subprocess.Popen, grace_s: float = KILL_GRACE_S) -> int | None:
    """SIGTERM the tree of `proc`, SIGKILL what is left after `grace_s`, reap `proc`; its exit code."""
    tree = tree_of(proc)
    kill_tree(proc, signal.SIGTERM, tree)
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(timeout=grace_s)
    kill_tree(proc, signal.SIGKILL, {**tree_of(proc), **tree})
    try:
        return proc.wait(timeout=grace_s)
    except subprocess.TimeoutExpired:
        return None


def communicate_group(
    proc: subprocess.Popen, timeout: float | None, input: str | bytes | None = None
) -> tuple[str | bytes | None, str | bytes | None]:
    """`proc.communicate(timeout=...)`; on timeout kill the whole tree and raise `GroupTimeout`."""
    try:
        return proc.communicate(input=input, timeout=timeout)
    except subprocess.TimeoutExpired:
        stop_group(proc, grace_s=1.0)
        out, err = proc.communicate()
        raise GroupTimeout(proc.args, timeout, output=out, stderr=err) from None
    except BaseException:  # KeyboardInterrupt in the caller: take the children down too
        stop_group(proc, grace_s=1.0)
        raise


def run_group(
    command: Sequence[str],
    timeout: float | None,
    capture_output: bool = True,
    text: bool = True,
    input: str | bytes | None = None,
    **popen_kwargs,
) -> subprocess.CompletedProcess:
    """`subprocess.run` that kills the whole process tree (not only the direct child) on timeout.

    Raises:
        GroupTimeout: the command ran past `timeout` seconds; every process it started was killed.
    """
    if capture_output:
        popen_kwargs.setdefault("stdout", subprocess.PIPE)
        popen_kwargs.setdefault("stderr", subprocess.PIPE)
    if input is not None:
        popen_kwargs["stdin"] = subprocess.PIPE
    proc = start_group(command, text=text, **popen_kwargs)
    out, err = communicate_group(proc, timeout, input=input)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


@contextlib.contextmanager
def running(command: Sequence[str], **popen_kwargs) -> Iterator[subprocess.Popen]:
    """`with running(cmd) as proc:` start `cmd` in its own session; on leaving the block (an assertion that
    failed included) whatever is still running of its tree is stopped."""
    proc = start_group(command, **popen_kwargs)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            stop_group(proc, grace_s=1.0)
        for stream in (proc.stdin, proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()
