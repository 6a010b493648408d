"""scripts/gpu_check.sh (bench/gpu_check.py) without a GPU: it exits at once in one line, its plan's commands
parse against the entry points they call, and a recorded run's table renders."""

from __future__ import annotations

import dataclasses
import importlib
import json
import shlex
import sys
from pathlib import Path

import pytest

from openfly_agent.utils.processes import run_group

REPO_ROOT = Path(__file__).resolve().parents[2]
GPU_CHECK = REPO_ROOT / "bench" / "gpu_check.py"


def run_gpu_check(*args: str, script=("bash", "scripts/gpu_check.sh")):
    env = {"PYTHON": sys.executable, "PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO_ROOT)}
    return run_group([*script, *args], timeout=120, cwd=REPO_ROOT, env=env)


@pytest.mark.skipif(importlib.import_module("torch").cuda.is_available(), reason="this machine has CUDA")
def test_without_cuda_it_exits_at_once_with_one_line():
    done = run_gpu_check()
    assert done.returncode == 2
    assert done.stdout == ""
    assert done.stderr.splitlines() == [
        "gpu_check: no CUDA device (torch.cuda.is_available() is False); run it on a machine with one CUDA GPU, "
        "or pass --plan to list its commands"
    ]


def test_the_plan_parses_against_the_entry_points(tmp_path):
    from accelerate.commands.launch import launch_command_parser

    from openfly_agent.eval.config import EvalConfig
    from openfly_agent.toolchain.__main__ import _parse_generate
    from openfly_agent.training.cli import parse_args
    from openfly_agent.training.stops import STOP_AFTER_STEPS_ENV
    from openfly_agent.utils.config import parse_config

    done = run_gpu_check("--plan", "--workdir", str(tmp_path))
    assert done.returncode == 0, done.stderr
    commands = [shlex.split(line) for line in done.stdout.splitlines()]
    envs = [
        dict(t.split("=", 1) for t in c[: c.index("python")]) for c in commands
    ]  # `NAME=value python ...`
    commands = [c[c.index("python") :] for c in commands]
    assert len(commands) == 8
    parsed = {"train": [], "eval": [], "generate": [], "bench": []}
    for tokens, env in zip(commands, envs):
        if tokens[1:3] == ["-m", "accelerate.commands.launch"]:
            launch = launch_command_parser().parse_args(tokens[3:])
            assert (REPO_ROOT / launch.config_file).is_file() and launch.training_script == "train.py"
            cfg = parse_args(
                launch.training_script_args
            )  # train.py's own parser: config file and every value
            assert cfg.init.checkpoint == str(tmp_path / "openvla-7b") and cfg.data.root == str(
                tmp_path / "data"
            )
            parsed["train"].append((Path(launch.config_file).name, cfg, env))
        elif tokens[1] == "eval.py":
            cfg = parse_config(EvalConfig, tokens[2:])
            assert cfg.checkpoint == str(tmp_path / "lora") and cfg.max_episodes == 4
            parsed["eval"].append(cfg)
        elif tokens[1:4] == ["-m", "openfly_agent.toolchain", "generate"]:
            cfg = _parse_generate(tokens[4:])
            assert cfg.scenes.train_seeds == [0, 1] and cfg.output_dir == str(tmp_path / "data")
            parsed["generate"].append(cfg)
        else:  # a bench script: each option it passes is one the script declares
            script = REPO_ROOT / tokens[1]
            assert tokens[1].startswith("bench/"), tokens
            if script.is_file():
                source = script.read_text()
                for option in (t.split("=")[0] for t in tokens[2:] if t.startswith("--")):
                    assert f'"{option}"' in source, f"{tokens[1]} has no {option}"
            parsed["bench"].append(tokens[1])
    launchers = [name for name, _, _ in parsed["train"]]
    assert launchers == ["single_gpu.yaml", "fsdp.yaml", "fsdp_offload.yaml"]
    lora, refused, offload = (cfg for _, cfg, _ in parsed["train"])
    assert lora.freeze_stage == "lora" and lora.steps == 12 and lora.batch.global_batch_size == 8
    assert refused.freeze_stage == offload.freeze_stage == "full"
    # the full fine-tune stops after its first step without the final save (the test-only stop)
    assert [env for _, _, env in parsed["train"]] == [
        {},
        {STOP_AFTER_STEPS_ENV: "1"},
        {STOP_AFTER_STEPS_ENV: "1"},
    ]
    assert not any(
        envs[i] for i, c in enumerate(commands) if c[1] != "-m" or c[2] != "accelerate.commands.launch"
    )
    assert len(parsed["eval"]) == len(parsed["generate"]) == 1
    assert parsed["bench"] == [
        "bench/synthetic_openvla.py",
        "bench/step_latency.py",
        "bench/train_throughput.py",
    ]


RECORDED = {
    "device": "NVIDIA H100 80GB HBM3 (79 GiB), torch 2.11.0+cu128",
    "results": [
        {"name": "wheels", "passed": True},
        {"name": "LoRA 12 steps + merge", "passed": True, "seconds": 95.4,
         "figures": {"train.py samples/s": 7.912, "peak GiB": 54.49, "merged": True}},
        {"name": "eval 4 episodes", "passed": False, "seconds": 12.0, "note": "exit code 1, expected 0"},
        {"name": "LoRA synthetic step", "passed": True, "seconds": 40.2,
         "figures": {"samples/s": 14.9, "MFU": 0.146, "peak GiB": None}},
        {"name": "FSDP offload, 1st step", "passed": None, "note": "skipped: dataset did not pass"},
    ],
}  # fmt: skip


def test_the_table_of_a_recorded_run(tmp_path):
    record = tmp_path / "gpu_check.json"
    record.write_text(json.dumps(RECORDED))
    done = run_gpu_check("--table", str(record), script=(sys.executable, str(GPU_CHECK)))
    assert done.returncode == 1  # a check failed
    lines = done.stdout.splitlines()
    assert lines[0] == "GPU check on NVIDIA H100 80GB HBM3 (79 GiB), torch 2.11.0+cu128"
    assert lines[2:9] == [
        "| check | result | s | figures |",
        "|---|---|---:|---|",
        "| wheels | pass | 0 |  |",
        "| LoRA 12 steps + merge | pass | 95 | train.py samples/s 7.9, peak GiB 54.5, merged yes |",
        "| eval 4 episodes | FAIL | 12 | exit code 1, expected 0 |",
        "| LoRA synthetic step | pass | 40 | samples/s 14.9, MFU 0.146, peak GiB - |",
        "| FSDP offload, 1st step | skipped | 0 | skipped: dataset did not pass |",
    ]
    assert lines[10] == "3 of 5 checks passed in 148 s"
    wheels = lines[11].removeprefix("wheels beyond a CUDA PyTorch image: ").split(", ")
    assert "transformers>=5.0,<6" in ", ".join(wheels) and "peft>=0.17" in wheels and "timm>=1.0.20" in wheels
    assert not any(w.startswith("torch>") for w in wheels)


def test_bench_lines_become_figures():
    gpu_check = bench_module()
    output = "\n".join(
        [
            "loading...",
            json.dumps({"preset": "openfly-7b", "history": "keyframe", "batch": 1, "ms_per_step": 47.5}),
            json.dumps({"preset": "openfly-7b", "history": "uniform", "batch": 16, "ms_per_step": 407.5}),
            json.dumps(
                {"config": "7b-lora-bf16", "samples_per_s": 14.9, "mfu": 0.146, "max_memory_gib": 54.5}
            ),
        ]
    )
    assert gpu_check.latency_figures(Path("."), output) == {"keyframe b1 ms": 47.5, "uniform b16 ms": 407.5}
    assert gpu_check.throughput_figures(Path("."), output) == {
        "samples/s": 14.9,
        "MFU": 0.146,
        "peak GiB": 54.5,
    }


def printing(line: str, times: int, code: int) -> list[str]:
    """A process that writes `line` `times` times on stderr and exits with `code`."""
    return [
        sys.executable,
        "-c",
        f"import sys; sys.stderr.write(({line!r} + '\\n') * {times}); sys.exit({code})",
    ]


def bench_module():
    sys.path.insert(0, str(REPO_ROOT / "bench"))
    return importlib.import_module("gpu_check")


HOST_REFUSAL = (
    "train.py: this run (full) keeps at least 112 GiB of model states in host memory with 1 process(es)"
)
GPU_REFUSAL = (
    "train.py: this run (full) needs at least 141 GiB per GPU with 1 process(es) (fsdp), more than ..."
)


@pytest.mark.parametrize(
    ("lines", "code", "passed"),
    [
        (1, 1, True),  # refused once, torchrun's exit code: the machine is too small, and says so
        (2, 1, False),  # printed twice
        (1, 2, False),  # not through the launcher the check runs
        (0, 1, False),  # failed without the refusal (e.g. killed): a failure
        (0, 0, True),  # trained: passes
    ],
)
def test_a_check_that_may_be_refused(tmp_path, lines, code, passed):
    gpu_check = bench_module()
    check = next(c for c in gpu_check.plan(tmp_path) if c.name == "FSDP offload, 1st step")
    check = dataclasses.replace(
        check, command=printing(HOST_REFUSAL, lines, code), needs=(), figures=lambda w, o: {}
    )
    result = gpu_check.run_check(check, tmp_path, {})
    assert result.passed is passed, result
    assert ("refused by the preflight" in result.note) == (passed and code == 1)
    assert (tmp_path / "logs" / "fsdp-offload-1st-step.log").is_file()


@pytest.mark.parametrize(
    ("code", "times", "passed"), [(1, 1, True), (1, 2, False), (0, 1, False), (2, 1, False)]
)
def test_the_one_gpu_refusal_passes_once_through_the_launcher(tmp_path, code, times, passed):
    gpu_check = bench_module()
    check = next(c for c in gpu_check.plan(tmp_path) if c.name == "full FT on 1 GPU refused")
    result = gpu_check.run_check(
        dataclasses.replace(check, command=printing(GPU_REFUSAL, times, code), needs=()), tmp_path, {}
    )
    assert result.passed is passed, result


def test_skipped_checks_are_named_by_their_table_name():
    done = run_gpu_check("--skip", "no such check", script=(sys.executable, str(GPU_CHECK)))
    assert done.returncode == 2
    assert "unknown check(s) ['no such check']" in done.stderr and "'LoRA synthetic step'" in done.stderr


def test_the_levers_suite_parses_against_its_scripts(tmp_path):
    """`--suite levers`: each command's arguments are accepted by the parser of the script it runs (the benches'
    `build_parser`, train.py's own), and the lever rows are the three levers, each alone."""
    from accelerate.commands.launch import launch_command_parser

    from openfly_agent.training.cli import parse_args

    done = run_gpu_check("--plan", "--suite", "levers", "--workdir", str(tmp_path))
    assert done.returncode == 0, done.stderr
    commands = [shlex.split(line) for line in done.stdout.splitlines()]
    assert len(commands) == 7
    levers, compiled = [], []
    for tokens in commands:
        if tokens[1:3] == ["-m", "accelerate.commands.launch"]:
            launch = launch_command_parser().parse_args(tokens[3:])
            cfg = parse_args(launch.training_script_args)
            assert cfg.use_lora and cfg.steps == 12 and not cfg.validation.final_eval
            assert not cfg.lora.merge_at_end and cfg.logging.log_interval == 4
            compiled.append(cfg.compile_layers)
        elif tokens[1] in ("bench/train_throughput.py", "bench/step_latency.py"):
            sys.path.insert(0, str(REPO_ROOT / "bench"))
            module = importlib.import_module(Path(tokens[1]).stem)
            args = module.build_parser().parse_args(tokens[2:])  # exits 2 on an option it lacks
            levers += getattr(args, "levers", [])
    assert levers == ["none", "fused_adamw", "compile_layers"]
    # train.py's time split, then the same run with its decoder layers compiled
    assert compiled == [False, True]


def test_the_time_split_and_lever_rows_become_figures(tmp_path):
    from openfly_agent.training.step_timer import PHASES

    gpu_check = bench_module()
    assert gpu_check.STEP_PHASES == PHASES  # the check reads the phases train.py logs
    logs = tmp_path / "lora-time" / "logs"
    logs.mkdir(parents=True)
    record = {"step": 12, "train/samples_per_s": 7.5, "train/tokens_per_s": 2600.0, "time/step_s": 1.2}
    record.update({f"time/{p}_s": 0.2 for p in gpu_check.STEP_PHASES})
    (logs / "metrics.jsonl").write_text(
        json.dumps({"step": 4, "time/step_s": 9.0}) + "\n" + json.dumps(record)
    )
    figures = gpu_check.time_split_figures(tmp_path, "")
    assert figures["s/step"] == 1.2 and figures["backward"] == 0.2 and figures["samples/s"] == 7.5
    assert figures["s/step by interval"] == "9.0 / 1.2"
    assert figures["MFU"] is None  # not logged: the row says "-"
    output = "\n".join(
        json.dumps(row)
        for row in (
            {
                "config": "7b-lora-bf16",
                "lever": "none",
                "samples_per_s": 14.0,
                "mfu": 0.2,
                "max_memory_gib": 50.0,
            },
            {"config": "7b-lora-bf16", "lever": "compile_layers", "failed": "BackendCompilerFailed: x"},
        )
    )
    assert gpu_check.lever_figures(tmp_path, output) == {
        "none samples/s": 14.0,
        "none MFU": 0.2,
        "none peak GiB": 50.0,
        "compile_layers failed": "BackendCompilerFailed: x",
    }


def test_the_record_is_rewritten_after_every_check(tmp_path, monkeypatch):
    """A run cut short keeps the rows it finished: the second check's own command reads the record and passes only
    if the first check's row is already in it, unfinished; at the end the record says `finished`."""
    gpu_check = bench_module()
    record = tmp_path / "gpu_check.json"
    reads_the_record = (
        "import json, sys; r = json.load(open(sys.argv[1])); "
        "sys.exit(0 if [x['name'] for x in r['results']] == ['wheels', 'first'] and not r['finished'] else 3)"
    )
    checks = [
        gpu_check.Check("first", [gpu_check.PY, "-c", "pass"], 60),
        gpu_check.Check("second", [gpu_check.PY, "-c", reads_the_record, str(record)], 60, needs=("first",)),
    ]
    monkeypatch.setattr(gpu_check, "plan", lambda workdir, suite="full": checks)
    results = gpu_check.run_all(tmp_path, "a test device")
    assert [(r.name, r.passed) for r in results][1:] == [("first", True), ("second", True)]
    written = json.loads(record.read_text())
    assert written["finished"] and written["device"] == "a test device"
    assert [r["name"] for r in written["results"]] == ["wheels", "first", "second"]


def test_the_table_of_a_run_cut_short_says_so(tmp_path):
    record = tmp_path / "gpu_check.json"
    record.write_text(json.dumps({**RECORDED, "finished": False}))
    done = run_gpu_check("--table", str(record), script=(sys.executable, str(GPU_CHECK)))
    assert done.stdout.splitlines()[-1] == (
        "the run stopped before its last check: the rows above are those it finished"
    )
