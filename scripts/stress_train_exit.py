"""Stress the end of a two-process training run: `torchrun --nproc_per_node 2 train.py` (gloo, CPU), repeated,
with busy processes competing for the cores. Every run must exit 0 within the timeout; a run that hangs is
killed with its whole process group (and, with --stacks, its native stacks are printed first).

    python scripts/stress_train_exit.py --runs 20 --load 2            # JSON line per run, then a summary line
    python scripts/stress_train_exit.py --runs 5 --dataset /tmp/tiny  # reuse a generated dataset

The training is the one of tests/training/test_train_distributed.py (tiny preset, 4 steps, checkpoints, final
evaluation); the dataset is generated with tests/training/tiny_dataset.yaml when --dataset has none.
Figures go to docs/BENCHMARKS.md ("Two-process training exit").
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from openfly_agent.utils.processes import GroupTimeout, run_group, start_group, stop_group, tree_of  # noqa: E402

TINY_DATASET_YAML = REPO / "tests" / "training" / "tiny_dataset.yaml"
BUSY_LOOP = "import time\nwhile True:\n    sum(i * i for i in range(10000))\n"


def train_args(dataset: Path, output_dir: Path, steps: int = 4) -> list[str]:
    """The two-process test's command line (configs/train/tiny.yaml with small batches, no TensorBoard)."""
    overrides = {
        "data.root": dataset, "output_dir": output_dir, "steps": steps, "batch.global_batch_size": 4,
        "batch.per_device_batch_size": 2, "optim.warmup_steps": 1, "logging.tracker": "none",
        "logging.log_interval": 1, "validation.interval": 0, "validation.final_max_samples": 9,
        "validation.per_device_batch_size": 4, "checkpoint.save_interval": 2, "checkpoint.keep_last": 5,
        "freeze_stage": "frozen_vision",
    }  # fmt: skip
    return ["--config_path", str(REPO / "configs/train/tiny.yaml")] + [
        f"--{k}={v}" for k, v in overrides.items()
    ]


def environment() -> dict[str, str]:
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}
    env.update(TOKENIZERS_PARALLELISM="false", OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    return env


def ensure_dataset(root: Path) -> Path:
    """A dataset under `root`, generated from tests/training/tiny_dataset.yaml when it has none."""
    if not (root / "Annotation" / "train.json").is_file():
        command = [sys.executable, "-m", "openfly_agent.toolchain", "generate", "--config_path", str(TINY_DATASET_YAML),
                   f"--output_dir={root}", "--plots=false"]  # fmt: skip
        done = run_group(command, timeout=900, env=environment(), cwd=REPO)
        if done.returncode != 0:
            raise SystemExit(f"dataset generation failed:\n{done.stderr[-3000:]}")
    return root


def native_stacks(pid: int) -> str:
    """`thread apply all bt` of `pid` through gdb (empty when gdb is missing or not allowed)."""
    if shutil.which("gdb") is None:
        return ""
    done = subprocess.run(
        ["gdb", "-p", str(pid), "-batch", "-ex", "thread apply all bt 30"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    return done.stdout[-12000:]


def one_run(dataset: Path, work: Path, timeout: float, stacks: bool) -> dict:
    """One two-process training run; {"ok", "rc", "seconds", "timed_out", ...}."""
    out = work / "run"
    shutil.rmtree(out, ignore_errors=True)
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    command = [*torchrun, str(REPO / "train.py"), *train_args(dataset, out)]
    start = time.monotonic()
    if stacks:  # keep the group alive on timeout long enough to look at it
        proc = start_group(command, cwd=REPO, env=environment(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True)  # fmt: skip
        try:
            _, err = proc.communicate(timeout=timeout)
            rc, timed_out = proc.returncode, False
        except subprocess.TimeoutExpired:
            for pid in tree_of(proc):
                print(f"--- stacks of pid {pid}", file=sys.stderr)
                print(native_stacks(pid), file=sys.stderr)
            stop_group(proc, grace_s=1.0)
            _, err = proc.communicate()
            rc, timed_out = None, True
        except BaseException:  # interrupted: take the run down with the script
            stop_group(proc, grace_s=1.0)
            raise
    else:
        try:
            done = run_group(command, timeout=timeout, cwd=REPO, env=environment())
            rc, err, timed_out = done.returncode, done.stderr, False
        except GroupTimeout as expired:
            rc, err, timed_out = None, expired.stderr or "", True
    seconds = time.monotonic() - start
    finished = (out / "checkpoints" / "last").exists()
    result = {
        "ok": rc == 0,
        "rc": rc,
        "timed_out": timed_out,
        "seconds": round(seconds, 1),
        "final_checkpoint": finished,
    }
    if rc != 0:
        result["stderr_tail"] = (err or "")[-2000:]
    return result


def stress(runs: int, load: int, timeout: float, dataset: Path | None = None, stacks: bool = False) -> dict:
    """`runs` two-process runs next to `load` busy processes; returns the summary (also printed per run)."""
    work = Path(tempfile.mkdtemp(prefix="stress-train-exit-"))
    busy = [start_group([sys.executable, "-c", BUSY_LOOP]) for _ in range(load)]
    results = []
    try:
        data = ensure_dataset(dataset or work / "dataset")
        for index in range(runs):
            result = {"run": index + 1, **one_run(data, work, timeout, stacks)}
            results.append(result)
            print(json.dumps(result), flush=True)
    finally:
        for proc in busy:
            stop_group(proc, grace_s=1.0)
        shutil.rmtree(work, ignore_errors=True)
    summary = {
        "runs": len(results), "passed": sum(r["ok"] for r in results),
        "timed_out": sum(r["timed_out"] for r in results), "load_processes": load, "timeout_s": timeout,
        "mean_s": round(sum(r["seconds"] for r in results) / max(1, len(results)), 1),
        "max_s": max((r["seconds"] for r in results), default=0.0),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.system()} {platform.release()}",
        "python": platform.python_version(),
    }  # fmt: skip
    print(json.dumps({"summary": summary}), flush=True)
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", type=int, default=20, help="two-process training runs (default: 20)")
    parser.add_argument(
        "--load", type=int, default=2, help="busy-loop processes competing for the CPU (default: 2)"
    )
    parser.add_argument(
        "--timeout", type=float, default=300.0, help="seconds per run before it counts as hung"
    )
    parser.add_argument(
        "--dataset", type=Path, default=None, help="a generated dataset (default: a fresh one)"
    )
    parser.add_argument("--stacks", action="store_true", help="print native stacks (gdb) of a hung run")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # `kill` still stops the busy loops and the runs
    summary = stress(args.runs, args.load, args.timeout, args.dataset, args.stacks)
    return 0 if summary["passed"] == summary["runs"] else 1


if __name__ == "__main__":
    sys.exit(main())
