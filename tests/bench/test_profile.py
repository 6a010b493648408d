"""`--profile` of the benches on the CPU: torch.profiler's table written to the file asked for."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import torch

from openfly_agent.utils.profiling import write_profile

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_write_profile_tables_the_operators_of_the_calls(tmp_path):
    a = torch.ones(16, 16)
    path = write_profile(lambda: a @ a, tmp_path / "sub" / "mm.txt", calls=3)
    text = path.read_text()
    assert text.startswith("# 3 call(s), sorted by self_cpu_time_total")
    mm = next(line for line in text.splitlines() if line.strip().startswith("aten::mm"))
    assert mm.split()[-1] == "3"  # the last column: number of calls


def test_step_latency_profiles_one_select_action(tmp_path):
    done = subprocess.run(
        [sys.executable, "bench/step_latency.py", "--presets", "tiny", "--batches", "1", "--steps", "1",
         "--warmup", "0", "--histories", "keyframe", "--profile", str(tmp_path / "select.txt")],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    (row,) = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    assert row["history"] == "keyframe" and row["ms_per_step"] > 0
    table = (tmp_path / "select-tiny-keyframe-b1.txt").read_text()
    assert table.startswith("# 1 call(s)") and "aten::" in table
