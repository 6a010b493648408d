"""Check a machine with one CUDA GPU and no network: the 7B chain at full size, FSDP's first step, the benches.

    bash scripts/gpu_check.sh                          # the same as: python bench/gpu_check.py
    python bench/gpu_check.py --plan                   # the commands it would run; nothing runs, no CUDA needed
    python bench/gpu_check.py --table <workdir>/gpu_check.json   # the table of a recorded run
    python bench/gpu_check.py --suite levers           # the speed levers, one at a time

In order, each as the command a user types, each with its own time limit (about 8.5 minutes in all on one
H200, measured): the synthetic OpenVLA-layout 7B folder (random weights, real key names and shapes, tokenizer
files); a small embedded dataset; the LoRA recipe for 12 steps from that folder (train.py's samples/s on real
data, its peak memory, the merged weights); `eval.py --checkpoint <the LoRA run folder>` for 4 episodes (it
loads the run's merged model); the full fine-tune under `fsdp.yaml` on one GPU, which the preflight must
refuse in one line before reading a weight; the full fine-tune under `fsdp_offload.yaml` through its first
optimizer step (or its one-line refusal on a host with too little memory for the offloaded states);
`bench/step_latency.py` (`select_action`, keyframe vs uniform, batch 1 and 16) and `bench/train_throughput.py`
(LoRA samples/s and MFU on synthetic batches). A check whose input failed is skipped. It prints one table and
writes `<workdir>/gpu_check.json`, rewritten after every check so that a run cut short keeps the rows it
finished (each command's output goes to `<workdir>/logs/`, torch.profiler's tables of `select_action` to
`<workdir>/profiles/`). Without CUDA it exits at once with one line (exit 2); with a failed check, exit 1. The
wheels it needs beyond a CUDA PyTorch image are pyproject.toml's dependencies but torch (printed with the
table; a missing one fails the `wheels` check).

`--suite levers` (about 5.5 minutes on one H200, measured in two parts) measures where the 7B LoRA step's time
goes and each speed lever alone: the synthetic folder and the dataset, then `train.py` (the LoRA recipe, 12 steps,
no merge, no final evaluation) with its time split, TFLOP/s and MFU from metrics.jsonl, the same run with
`--compile_layers=true`, `bench/step_latency.py` at batch 1 and 16 with its peak memory and profiles,
`bench/train_throughput.py --levers none fused_adamw` and, in its own check, `--levers compile_layers`
(samples/s, MFU and peak memory of each).
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import re
import shlex
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path

from openfly_agent.utils.processes import GroupTimeout, run_group

REPO_ROOT = Path(__file__).resolve().parents[1]
EXIT_OK, EXIT_FAILED, EXIT_NO_CUDA = 0, 1, 2
# train.py's refusal exits 2; torchrun (accelerate's launcher under FSDP) reports a failed child as 1
LAUNCHER_FAILED = 1
PY = "python"  # the interpreter running this file replaces it when a check runs
TRAIN = [PY, "-m", "accelerate.commands.launch", "--config_file"]  # `accelerate launch`, this interpreter
# the synthetic 7B LoRA step of the bench, batch 8, 5 steps (the levers checks add `--levers ...`)
LORA_BENCH = [PY, "bench/train_throughput.py", "--configs", "7b-lora-bf16", "--batch", "8", "--steps", "5"]
FULL_FT_BUDGET = [  # the full fine-tune through its first optimizer step only (with FIRST_STEP_ONLY)
    "--steps=1", "--batch.global_batch_size=2", "--batch.per_device_batch_size=2",
    "--validation.interval=0", "--validation.final_eval=false", "--logging.tracker=none", "--data.num_workers=2",
]  # fmt: skip


# train.py's test-only stop (training/stops.py, STOP_AFTER_STEPS_ENV): exit after step 1 without the final save,
# whose checkpoint of a 7.5 B full fine-tune is ~90 GB
FIRST_STEP_ONLY = {"OPENFLY_STOP_AFTER_STEPS": "1"}


STEP_PHASES = ("data", "forward", "backward", "optimizer", "other")  # training/step_timer.py's PHASES
SUITES = {
    "full": (
        "openvla folder", "dataset", "LoRA 12 steps + merge", "eval 4 episodes", "full FT on 1 GPU refused",
        "FSDP offload, 1st step", "select_action latency", "LoRA synthetic step",
    ),
    "levers": (
        "openvla folder", "dataset", "LoRA 12 steps, time split", "LoRA 12 steps, compiled layers",
        "select_action latency", "LoRA step, levers",
        "LoRA step, compiled layers",
    ),
}  # fmt: skip


@dataclass
class Check:
    """One command and what its outputs say.

    Attributes:
        name: the table's row.
        command: argv (`python` stands for this interpreter).
        timeout_s: killed with every process it started after this long.
        needs: checks that must have passed first.
        expect_rc: the exit code that passes.
        env: environment variables it runs with, beside the offline switches every check gets.
        figures: reads the figures from (workdir, the command's stdout + stderr).
        stderr_pattern: exactly one stderr line must match it (a refusal is printed once).
        or_refused: a preflight refusal that passes too, printed once, with torchrun's exit code 1 (the table
            says so): a machine too small for the check must be told so, not killed.
    """

    name: str
    command: list[str]
    timeout_s: int
    needs: tuple[str, ...] = ()
    expect_rc: int = 0
    env: dict[str, str] = field(default_factory=dict)
    figures: Callable[[Path, str], dict] = lambda workdir, output: {}
    stderr_pattern: str | None = None
    or_refused: str | None = None


@dataclass
class CheckResult:
    """What one check gave (`passed`: None when skipped)."""

    name: str
    passed: bool | None
    seconds: float = 0.0
    figures: dict = field(default_factory=dict)
    note: str = ""


def json_lines(output: str) -> list[dict]:
    """The JSON objects printed one per line (the benches' format)."""
    rows = []
    for line in output.splitlines():
        if line.startswith("{"):
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return rows


def run_metrics(run: Path, prefixes: tuple[str, ...] = ("train/",)) -> dict:
    """The last value of each figure of a run's logs/metrics.jsonl whose name starts with one of `prefixes`."""
    last: dict = {}
    path = run / "logs" / "metrics.jsonl"
    for line in path.read_text().splitlines() if path.is_file() else []:
        last.update({k: v for k, v in json.loads(line).items() if k.startswith(prefixes)})
    return last


def lora_figures(workdir: Path, output: str) -> dict:
    metrics = run_metrics(workdir / "lora")
    return {
        "train.py samples/s": metrics.get("train/samples_per_s"),
        "peak GiB": metrics.get("train/memory_allocated_gib"),
        "merged": (workdir / "lora" / "merged" / "config.json").is_file(),
    }


def time_split_command(w: str, init: list[str], run: str, *extra: str) -> list[str]:
    """train.py, the 7B LoRA recipe for 12 steps at batch 8 from the synthetic folder, logged every 4 steps, no
    merge, no evaluation (`extra`: the lever under test)."""
    return [
        *TRAIN, "configs/accelerate/single_gpu.yaml", "train.py", "--config_path", "configs/train/openfly-7b-lora.yaml",
        *init, f"--output_dir={w}/{run}", "--steps=12", "--batch.global_batch_size=8",
        "--batch.per_device_batch_size=8", "--validation.interval=0", "--validation.final_eval=false",
        "--checkpoint.save_interval=0", "--lora.merge_at_end=false", "--logging.tracker=none",
        "--logging.log_interval=4", "--data.num_workers=4", *extra,
    ]  # fmt: skip


def interval_step_seconds(run: Path) -> list[float]:
    """`time/step_s` of every logged interval of a run, in order (the first holds the warm-up)."""
    path = run / "logs" / "metrics.jsonl"
    lines = path.read_text().splitlines() if path.is_file() else []
    return [round(r["time/step_s"], 3) for r in map(json.loads, lines) if "time/step_s" in r]


def time_split_figures(workdir: Path, output: str, run: str = "lora-time") -> dict:
    """train.py's last logged interval: seconds per step and its split, tokens/s, MFU, peak memory; and the
    seconds per step of every interval."""
    metrics = run_metrics(workdir / run, ("train/", "time/", "throughput/"))
    figures = {"s/step": metrics.get("time/step_s")}
    figures.update({phase: metrics.get(f"time/{phase}_s") for phase in STEP_PHASES})
    figures.update(
        {
            "samples/s": metrics.get("train/samples_per_s"),
            "tokens/s": metrics.get("train/tokens_per_s"),
            "MFU": metrics.get("throughput/mfu"),
            "peak GiB": metrics.get("train/memory_allocated_gib"),
            "s/step by interval": " / ".join(map(str, interval_step_seconds(workdir / run))) or None,
        }
    )
    return figures


def fsdp_figures(workdir: Path, output: str) -> dict:
    metrics = run_metrics(workdir / "full-offload")
    return {"loss": metrics.get("train/loss"), "peak GiB": metrics.get("train/memory_allocated_gib")}


def latency_figures(workdir: Path, output: str) -> dict:
    figures = {}
    for row in json_lines(output):
        if row.get("preset") != "openfly-7b":
            continue
        figures[f"{row['history']} b{row['batch']} ms"] = row.get("ms_per_step")
        if row.get("max_memory_gib") is not None:
            figures[f"{row['history']} b{row['batch']} GiB"] = row["max_memory_gib"]
    return figures


def throughput_figures(workdir: Path, output: str) -> dict:
    rows = [row for row in json_lines(output) if row.get("config") == "7b-lora-bf16"]
    if not rows:
        return {}
    row = rows[-1]
    return {
        "samples/s": row.get("samples_per_s"),
        "MFU": row.get("mfu"),
        "peak GiB": row.get("max_memory_gib"),
    }


def lever_figures(workdir: Path, output: str) -> dict:
    """samples/s, MFU and peak memory of each lever row of bench/train_throughput.py (or why it failed)."""
    figures: dict = {}
    for row in json_lines(output):
        if row.get("config") != "7b-lora-bf16" or "lever" not in row:
            continue
        lever = row["lever"]
        if "failed" in row:
            figures[f"{lever} failed"] = row["failed"][:80]
            continue
        figures.update(
            {
                f"{lever} samples/s": row.get("samples_per_s"),
                f"{lever} MFU": row.get("mfu"),
                f"{lever} peak GiB": row.get("max_memory_gib"),
            }
        )
    return figures


def eval_figures(workdir: Path, output: str) -> dict:
    episodes = list((workdir / "eval").rglob("episodes.jsonl"))
    count = sum(len(path.read_text().splitlines()) for path in episodes)
    return {"episodes": count}


def plan(workdir: Path, suite: str = "full") -> list[Check]:
    """The checks of `suite` (`SUITES`), in order, with their commands (paths under `workdir`)."""
    return [check for check in all_checks(workdir) if check.name in SUITES[suite]]


def all_checks(workdir: Path) -> list[Check]:
    """Every check of every suite, in the order they run."""
    w = str(workdir)
    openvla, data = f"{w}/openvla-7b", f"{w}/data"
    init = [f"--init.checkpoint={openvla}", f"--model.llm.tokenizer_path={openvla}", f"--data.root={data}"]
    full = ["train.py", "--config_path", "configs/train/openfly-7b-full.yaml", *init]
    return [
        Check("openvla folder", [PY, "bench/synthetic_openvla.py", "--size", "full", "--out", openvla], 300),
        Check(
            "dataset",
            [
                PY,
                "-m",
                "openfly_agent.toolchain",
                "generate",
                "--config_path",
                "configs/toolchain/embedded-small.yaml",
                f"--output_dir={data}",
                "--workers=8",
                "--scenes.train_seeds=[0,1]",
                "--scenes.unseen_seeds=[1000]",
                "--scenes.trajectories_per_scene=20",
            ],
            120,
        ),  # fmt: skip
        Check(
            "LoRA 12 steps + merge",
            [
                *TRAIN,
                "configs/accelerate/single_gpu.yaml",
                "train.py",
                "--config_path",
                "configs/train/openfly-7b-lora.yaml",
                *init,
                f"--output_dir={w}/lora",
                "--steps=12",
                "--batch.global_batch_size=8",
                "--batch.per_device_batch_size=8",
                "--validation.interval=0",
                "--validation.final_max_samples=32",
                "--checkpoint.save_interval=0",
                "--logging.tracker=none",
                "--logging.log_interval=4",
                "--data.num_workers=4",
            ],
            300,
            needs=("openvla folder", "dataset"),
            figures=lora_figures,
        ),  # fmt: skip
        Check(
            "LoRA 12 steps, time split",
            time_split_command(w, init, "lora-time"),
            240,
            needs=("openvla folder", "dataset"),
            figures=partial(time_split_figures, run="lora-time"),
        ),
        Check(
            "LoRA 12 steps, compiled layers",
            time_split_command(w, init, "lora-time-compiled", "--compile_layers=true"),
            300,
            needs=("openvla folder", "dataset"),
            figures=partial(time_split_figures, run="lora-time-compiled"),
        ),
        Check(
            "eval 4 episodes",
            [
                PY,
                "eval.py",
                "--checkpoint",
                f"{w}/lora",  # the run folder: eval.py takes its merged model
                "--sim.type=embedded",
                "--split=[test_unseen]",
                "--max_episodes=4",
                f"--dataset_root={data}",
                f"--output_dir={w}/eval",
                "--plots=0",
                "--progress=false",
            ],
            150,
            needs=("LoRA 12 steps + merge",),
            figures=eval_figures,
        ),  # fmt: skip
        Check(
            "full FT on 1 GPU refused",
            [
                *TRAIN,
                "configs/accelerate/fsdp.yaml",
                "--num_processes",
                "1",
                *full,
                f"--output_dir={w}/full",
                *FULL_FT_BUDGET,
            ],
            120,
            needs=("dataset",),
            expect_rc=LAUNCHER_FAILED,
            env=FIRST_STEP_ONLY,
            stderr_pattern=r"^train\.py: this run .* needs at least \d+ GiB per GPU",
        ),  # fmt: skip
        Check(
            "FSDP offload, 1st step",
            [
                *TRAIN,
                "configs/accelerate/fsdp_offload.yaml",
                "--num_processes",
                "1",
                *full,
                f"--output_dir={w}/full-offload",
                *FULL_FT_BUDGET,
                "--logging.log_interval=1",
            ],
            300,
            needs=("openvla folder", "dataset"),
            env=FIRST_STEP_ONLY,
            figures=fsdp_figures,
            or_refused=r"^train\.py: this run .* keeps at least \d+ GiB of model states in host memory",
        ),  # fmt: skip
        Check(
            "select_action latency",
            [
                PY,
                "bench/step_latency.py",
                "--presets",
                "openfly-7b",
                "--batches",
                "1",
                "16",
                "--steps",
                "10",
                "--profile",
                f"{w}/profiles/select_action.txt",
            ],  # fmt: skip
            150,
            figures=latency_figures,
        ),
        Check(
            "LoRA synthetic step",
            LORA_BENCH,
            150,
            figures=throughput_figures,
        ),
        Check(
            "LoRA step, levers",
            [*LORA_BENCH, "--levers", "none", "fused_adamw"],
            150,
            figures=lever_figures,
        ),  # fmt: skip
        Check(  # its own check: a compilation that fails or runs long costs the other levers nothing
            "LoRA step, compiled layers",
            [*LORA_BENCH, "--levers", "compile_layers"],
            180,
            figures=lever_figures,
        ),  # fmt: skip
    ]


def required_wheels() -> list[str]:
    """pyproject.toml's dependencies but torch (a CUDA PyTorch image brings it), as `name>=version`."""
    text = (REPO_ROOT / "pyproject.toml").read_text()
    block = re.search(r"^dependencies = \[(.*?)^\]", text, re.S | re.M).group(1)
    dependencies = re.findall(r'^\s*"([^"]+)"', block, re.M)
    return [d for d in dependencies if re.split(r"[<>=!~ ]", d, maxsplit=1)[0] != "torch"]


def missing_wheels() -> list[str]:
    missing = []
    for requirement in required_wheels():
        name = re.split(r"[<>=!~ \[]", requirement, maxsplit=1)[0]
        try:
            importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            missing.append(name)
    return missing


def printed_once(pattern: str, stderr: str) -> bool:
    """Whether exactly one line of `stderr` matches `pattern`."""
    return sum(re.search(pattern, line) is not None for line in stderr.splitlines()) == 1


def run_check(check: Check, workdir: Path, passed: dict[str, bool]) -> CheckResult:
    """Run one check (unless an input failed), its output kept in `<workdir>/logs/<name>.log`."""
    failed_inputs = [need for need in check.needs if not passed.get(need)]
    if failed_inputs:
        return CheckResult(check.name, None, note=f"skipped: {', '.join(failed_inputs)} did not pass")
    command = [sys.executable if token == PY else token for token in check.command]
    env = {
        **os.environ,
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "TRANSFORMERS_OFFLINE": "1",
        **check.env,
    }
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), env.get("PYTHONPATH", "")])
    start = time.perf_counter()
    try:
        done = run_group(command, timeout=check.timeout_s, cwd=REPO_ROOT, env=env)
        rc, out, err = done.returncode, done.stdout or "", done.stderr or ""
    except GroupTimeout as timeout:
        rc, out, err = None, str(timeout.output or ""), str(timeout.stderr or "")
    seconds = time.perf_counter() - start
    log = workdir / "logs" / f"{re.sub(r'[^a-z0-9]+', '-', check.name.lower()).strip('-')}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    shown = [f"{name}={value}" for name, value in check.env.items()] + command
    log.write_text(f"$ {shlex.join(shown)}\n# exit code {rc}\n{out}\n--- stderr ---\n{err}")
    if rc is None:
        return CheckResult(check.name, False, seconds, note=f"timed out after {check.timeout_s} s ({log})")
    ok = rc == check.expect_rc
    if ok and check.stderr_pattern is not None:
        ok = printed_once(check.stderr_pattern, err)
    if (
        not ok
        and check.or_refused is not None
        and rc == LAUNCHER_FAILED
        and printed_once(check.or_refused, err)
    ):
        return CheckResult(
            check.name, True, seconds, note=f"refused by the preflight, as it should be here ({log})"
        )
    figures = check.figures(workdir, out + "\n" + err) if ok else {}
    note = "" if ok else f"exit code {rc}, expected {check.expect_rc} ({log})"
    return CheckResult(check.name, ok, seconds, figures, note)


def format_value(value) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 1 else f"{value:,.1f}"
    return "-" if value is None else str(value)


def render_table(results: list[CheckResult], device: str) -> str:
    """The markdown table of the checks, with the device, the verdict and the wheels line."""
    lines = [f"GPU check on {device}", "", "| check | result | s | figures |", "|---|---|---:|---|"]
    for r in results:
        verdict = {True: "pass", False: "FAIL", None: "skipped"}[r.passed]
        figures = ", ".join(f"{k} {format_value(v)}" for k, v in r.figures.items())
        detail = "; ".join(x for x in (figures, r.note) if x)
        lines.append(f"| {r.name} | {verdict} | {r.seconds:.0f} | {detail} |")
    failed = [r.name for r in results if not r.passed]
    total = sum(r.seconds for r in results)
    lines += ["", f"{len(results) - len(failed)} of {len(results)} checks passed in {total:.0f} s"]
    lines.append("wheels beyond a CUDA PyTorch image: " + ", ".join(required_wheels()))
    return "\n".join(lines)


def record_path(workdir: Path) -> Path:
    return workdir / "gpu_check.json"


def write_record(workdir: Path, device: str, results: list[CheckResult], finished: bool) -> None:
    """`<workdir>/gpu_check.json`, rewritten after every check: a run cut short (a lease that ends, a kill) keeps
    the rows it finished, and `finished` says whether every check of the suite ran."""
    record = {"device": device, "finished": finished, "results": [asdict(r) for r in results]}
    record_path(workdir).write_text(json.dumps(record, indent=1))


def run_all(workdir: Path, device: str, skip: tuple[str, ...] = (), suite: str = "full") -> list[CheckResult]:
    """Every check of the suite's `plan` in order but those named in `skip` (left out of the table), the record
    rewritten after each."""
    missing = missing_wheels()
    results = [CheckResult("wheels", not missing, note=f"missing: {', '.join(missing)}" if missing else "")]
    write_record(workdir, device, results, finished=False)
    passed: dict[str, bool] = {}
    for check in plan(workdir, suite):
        if check.name in skip:
            continue
        result = run_check(check, workdir, passed)
        passed[check.name] = bool(result.passed)
        results.append(result)
        write_record(workdir, device, results, finished=False)
        print(f"{result.name}: {'pass' if result.passed else 'FAIL' if result.passed is False else 'skipped'} "
              f"({result.seconds:.0f} s)", file=sys.stderr, flush=True)  # fmt: skip
    write_record(workdir, device, results, finished=True)
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", default="outputs/gpu_check", help="where folders, logs and results go")
    parser.add_argument("--plan", action="store_true", help="print the commands, one a line; run nothing")
    parser.add_argument(
        "--suite", default="full", choices=sorted(SUITES),
        help="full: the whole check (default); levers: the time split and each speed lever alone",
    )  # fmt: skip
    parser.add_argument("--table", metavar="JSON", help="print the table of a recorded gpu_check.json")
    parser.add_argument(
        "--skip", nargs="+", default=[], metavar="CHECK",
        help="checks to leave out, by their table name (a check that needs one of them is skipped too)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    workdir = Path(args.workdir).resolve()
    checks = plan(workdir, args.suite)
    unknown = sorted(set(args.skip) - {check.name for check in checks})
    if unknown:
        parser.error(f"unknown check(s) {unknown}; the checks: {[check.name for check in checks]}")
    if args.plan:
        for check in checks:
            print(shlex.join([f"{name}={value}" for name, value in check.env.items()] + check.command))
        return EXIT_OK
    if args.table:
        record = json.loads(Path(args.table).read_text())
        results = [CheckResult(**r) for r in record["results"]]
        print(render_table(results, record["device"]))
        if not record.get("finished", True):  # records before the field were written at the end only
            print("the run stopped before its last check: the rows above are those it finished")
        return EXIT_OK if all(r.passed for r in results) else EXIT_FAILED
    import torch

    if not torch.cuda.is_available():
        print("gpu_check: no CUDA device (torch.cuda.is_available() is False); run it on a machine with one "
              "CUDA GPU, or pass --plan to list its commands", file=sys.stderr)  # fmt: skip
        return EXIT_NO_CUDA
    workdir.mkdir(parents=True, exist_ok=True)
    device = f"{torch.cuda.get_device_name(0)} ({torch.cuda.mem_get_info(0)[1] / 2**30:.0f} GiB), torch {torch.__version__}"
    results = run_all(workdir, device, tuple(args.skip), args.suite)
    print(render_table(results, device))
    return EXIT_OK if all(r.passed for r in results) else EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
