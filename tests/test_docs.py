"""Docs that run (issue 14): every command of README.md, docs/*.md (RESULTS.md included) and docs/experiments/
names options its entry point has, and the fenced command blocks that can run on a CPU run on small data, from a
fresh working directory; every Python snippet's imports resolve, and the self-contained ones run. The experiment
log's blocks are not run: its entries are historical records (appended, never rewritten), so only their options
are checked against today's parsers.

Options of every command (tests/docs_commands.py finds them) are checked against the real parsers: draccus
config dataclasses (train.py, eval.py, and each command of the toolchain, hub and simulator), bench/ and
scripts/ files by their source. A command block runs as documented, with small-data budget options appended
(a few steps, episodes or trajectories) and the tiny test dataset standing in for embedded-small; blocks that
train are marked `slow`.

Docs that cannot drift (issue 46): every backticked repository path (`configs/train/tiny.yaml`, `model/agent.py`)
and every backticked `module.name` / `name()` (`openfly_agent.eval.compare`, `train()`, `agent.forward`) of
README.md, docs/*.md and data_cards/*.md resolves against the tree ("paths and names in prose" below says what
counts as either). The experiment log is exempt from that check: a dated entry records the code of its day and
may rightly name files and functions deleted since, and it is never rewritten.
"""

from __future__ import annotations

import ast
import builtins
import dataclasses
import fnmatch
import functools
import importlib
import importlib.util
import json
import os
import re
import shutil
import sys
from pathlib import Path

import pytest
from docs_commands import DOC_FILES, HISTORICAL, REPO, DocCommand, DocSnippet, doc_commands, doc_snippets
from eval_helpers import generate_tiny_dataset

from openfly_agent import constants as C
from openfly_agent.recipe.config import RecipeConfig
from openfly_agent.toolchain.config import GroundingDataConfig
from openfly_agent.utils.cli_options import check_options
from openfly_agent.utils.processes import run_group

COMMANDS = doc_commands()
SNIPPETS = doc_snippets()
DATASET = "outputs/datasets/embedded-small"
EXECUTABLE = {
    "train",
    "eval",
    "toolchain:generate",
    "toolchain:summarize",
    "hub:release",
    "hub:release-dataset",
}
EXECUTABLE |= {"sim:render", "sim:export", "sim:landmarks", "toolchain:grounding", "compare:None"}
# Small-data budgets appended to an executed command (later options win).
BUDGET = {
    "train": [
        "--steps=2", "--batch.global_batch_size=4", "--batch.per_device_batch_size=2", "--validation.interval=0",
        "--validation.final_max_samples=4", "--logging.tracker=none", "--checkpoint.save_interval=0",
        "--time_limit_minutes=10",
    ],
    "eval": ["--max_episodes=1", "--max_steps=3", "--plots=0", "--progress=false", "--batch_size=2", "--torch_threads=1"],
    "compare:None": ["--resamples=200"],
    "toolchain:generate": [
        "--workers=0", "--plots=false", "--scenes.train_seeds=[0]", "--scenes.unseen_seeds=[1]",
        "--scenes.trajectories_per_scene=3", "--scenes.test_seen_fraction=0.5", "--scenes.city_size_m=300",
        "--scenes.city_buildings=30", "--route.height_min_m=10", "--route.height_max_m=40", "--route.min_dist_m=40",
        "--route.max_dist_m=90", "--categories.height_bins_m=[25,40]", "--categories.length_bins_m=[50,100]",
        "--render.width=64", "--render.height=64", "--dagger.episodes_per_scene=0",
    ],
    "sim:render": ["--width=64", "--height=64", "--size_m=300"],
    "toolchain:grounding": ["--yaw_copies=0"],
    "sim:export": ["--size_m=300", "--spacing=8"],
    "sim:landmarks": ["--size_m=300"],
}  # fmt: skip


def _id(command: DocCommand) -> str:
    return f"{command.file}:{command.line}"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"{name}_entry_point", REPO / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _strip(args: list[str], names: tuple[str, ...]) -> list[str]:
    out, skip = [], False
    for arg in args:
        if skip:
            skip = False
        elif arg in names:
            skip = True
        elif not any(arg.startswith(f"{name}=") for name in names):
            out.append(arg)
    return out


# Options an experiment-log entry used that were deleted later, with the entry that says so and a commit that
# still has them: the historical commands keep them (entries are never rewritten).
RETIRED_OPTIONS = {
    # docs/experiments/2026-11-27-deleted-research-switches.md (commit 7544758)
    "model.vision.cnn_fine_fusion", "model.vision.cnn_instruction_film", "model.vision.cnn_init",
    "model.vision.cnn_stem_width", "model.grounding.subcells", "model.grounding.attribute_match",
    "model.grounding.dense_attribute_weight", "model.grounding.cell_fusion_layers",
    "data.expression_area_power", "data.group_by_kind",
    # docs/experiments/2026-11-28-no-reversal-decoding.md (commit 55ef66f)
    "agent.no_reversal",
    # docs/experiments/2026-11-28-long-route-ablation.md (commit 9046d6d)
    "model.action_head.stop_loss_weight",
    # docs/experiments/2026-11-28-rl-stage-on-the-main-job.md (commit d431633)
    "rl.progress_at_stop",
    # docs/experiments/2026-11-28-long-route-ablation.md (commit 1cb4fad)
    "model.action_head.leg_goal_weight",
    # docs/experiments/2026-11-29-stop-margin.md (commit ec77d5b)
    "agent.stop_margin",
    # docs/experiments/2026-11-29-main-job-expression-frames-in-navigation.md (commit 00c660f)
    "data.expression_fraction",
    # docs/experiments/2026-11-29-main-job-action-history.md (commit 5925c14)
    "model.prompt.action_history",
    # docs/experiments/2026-11-30-main-job-own-boxes.md (commit d6f1b4e)
    "model.action_head.box_token_predicted_fraction",
}  # fmt: skip


def without_retired_options(command: DocCommand) -> DocCommand:
    """An experiment-log command without the options deleted since (other documents keep every option)."""
    if not (REPO / command.file).is_relative_to(HISTORICAL):
        return command
    kept = [a for a in command.args if not (a.startswith("--") and a[2:].split("=", 1)[0] in RETIRED_OPTIONS)]
    return dataclasses.replace(command, args=kept)


def check_command(command: DocCommand) -> None:
    """The command names an entry point that exists and options that entry point has (values parse too when
    the command is complete, not a fragment with placeholders)."""
    command = without_retired_options(command)
    where = command.where
    for flag, value in zip(command.launcher, command.launcher[1:]):
        if flag == "--config_file":
            assert (REPO / value).is_file(), f"{where}: no accelerate config {value}"
    complete = command.block is not None and not command.has_placeholders and "..." not in command.text
    if {"--help", "-h"} & {command.sub, *command.args}:  # every entry point has it (tests/test_cli_help.py)
        return
    if command.kind == "train":
        from openfly_agent.training.config import TrainConfig

        train = _load("train")
        check_options(TrainConfig, train.with_default_config(command.args))
        if complete:
            train.parse_args(command.args)
    elif command.kind == "eval":
        from openfly_agent.eval.config import EvalConfig
        from openfly_agent.utils.config import parse_config

        check_options(EvalConfig, command.args)
        if complete:
            parse_config(EvalConfig, command.args)
    elif command.kind == "toolchain":
        from openfly_agent.toolchain import __main__ as toolchain
        from openfly_agent.toolchain.config import GenerateConfig

        assert command.sub in toolchain.COMMANDS, f"{where}: no toolchain command {command.sub!r}"
        if command.sub in ("generate", "dagger"):  # dagger: GenerateConfig's fields and its checkpoint
            config = GenerateConfig if command.sub == "generate" else toolchain.DaggerCommandConfig
            argv = _strip(command.args, ("--agent_class",))
            check_options(config, argv)
            if complete:
                toolchain._parse_command_config(config, toolchain._generate_args(argv), command.sub)
        elif command.sub == "grounding":
            check_options(GroundingDataConfig, command.args)
        elif command.sub == "dagger-round":
            check_options(toolchain.DaggerRoundCommandConfig, _strip(command.args, ("--agent_class",)))
        else:
            config = toolchain.SummarizeConfig if command.sub == "summarize" else toolchain.SegmentConfig
            check_options(config, command.args)
    elif command.kind == "hub":
        from openfly_agent.hub.cli import COMMANDS as HUB_COMMANDS

        if command.sub is not None:
            assert command.sub in HUB_COMMANDS, f"{where}: no hub command {command.sub!r}"
            check_options(HUB_COMMANDS[command.sub][0], command.args)
    elif command.kind == "recipe":
        check_options(RecipeConfig, command.args)
    elif command.kind == "compare":
        from openfly_agent.eval.compare import CompareConfig, command_args

        check_options(CompareConfig, command_args(command.args))
    elif command.kind == "seeds":
        from openfly_agent.eval.seeds import SeedsConfig
        from openfly_agent.eval.seeds import command_args as seeds_args

        check_options(SeedsConfig, seeds_args(command.args))
    elif command.kind == "sim":
        from openfly_agent.sim.cli import COMMANDS as SIM_COMMANDS

        if command.sub is not None:
            assert command.sub in SIM_COMMANDS, f"{where}: no sim command {command.sub!r}"
            check_options(SIM_COMMANDS[command.sub][0], command.args)
    elif command.kind in ("script", "shell"):
        path = REPO / command.sub
        assert path.is_file(), f"{where}: no file {command.sub}"
        source = path.read_text()
        # a wrapper that hands its arguments to a Python script (`exec "$PYTHON" bench/x.py "$@"`) has its options
        passed_on = re.search(r'exec "\$PYTHON" (\S+\.py) "\$@"', source)
        if passed_on:
            source += (REPO / passed_on.group(1)).read_text()
        args, forwarded = command.args, []
        if "--" in args:  # a bench that builds a training run: what follows a bare -- are train.py's options
            from openfly_agent.training.config import TrainConfig

            args, forwarded = args[: args.index("--")], args[args.index("--") + 1 :]
            check_options(TrainConfig, forwarded)
        for flag in [a.split("=", 1)[0] for a in args if a.startswith("--")]:
            assert f'"{flag}"' in source, f"{where}: {command.sub} has no option {flag}"


@pytest.mark.parametrize("command", [c for c in COMMANDS if c.kind != "other"], ids=_id)
def test_documented_commands_use_real_options(command):
    check_command(command)


def test_the_stale_eval_command_of_issue_14_is_caught():
    from docs_commands import parse_command

    from openfly_agent.utils.cli_options import UnknownOptionError

    stale = parse_command("docs/TRAINING.md", 0, "python eval.py --agent_path=runs/tiny")
    with pytest.raises(UnknownOptionError, match="--agent_path"):
        check_command(stale)
    assert len(COMMANDS) > 50 and {c.kind for c in COMMANDS} >= {"train", "eval", "toolchain", "hub", "sim"}


def test_a_bench_forwards_what_follows_a_bare_dash_dash_to_train_options():
    from docs_commands import parse_command

    from openfly_agent.utils.cli_options import UnknownOptionError

    good = parse_command(
        "docs/x.md", 0, "python bench/grounding_step.py --steps 2 -- --model.llm.length_groups=3"
    )
    check_command(good)
    stale = parse_command(
        "docs/x.md", 0, "python bench/grounding_step.py --steps 2 -- --model.llm.length_grups=3"
    )
    with pytest.raises(UnknownOptionError, match="length_grups"):
        check_command(stale)
    with pytest.raises(AssertionError, match="no option --step"):
        check_command(parse_command("docs/x.md", 0, "python bench/grounding_step.py --step 2"))


def test_every_config_file_the_docs_name_exists():
    """Also in prose and in environment variables (`RECIPE_CONFIG=configs/...`), which no parser reads."""
    named = [
        (doc, path) for doc in DOC_FILES for path in re.findall(r"configs/[\w./-]+\.yaml", doc.read_text())
    ]
    missing = [f"{doc.relative_to(REPO)}: {path}" for doc, path in named if not (REPO / path).is_file()]
    assert len(named) > 50 and not missing, "\n".join(missing)


def test_every_document_is_checked_and_the_results_name_their_commands():
    checked = {path.relative_to(REPO).as_posix() for path in DOC_FILES}
    shipped = {p.relative_to(REPO).as_posix() for p in [REPO / "README.md", *(REPO / "docs").rglob("*.md")]}
    assert checked == shipped
    results = [c for c in COMMANDS if c.file == "docs/RESULTS.md"]
    kinds = {c.kind for c in results}
    assert {"recipe", "script", "shell"} <= kinds, kinds  # the recipe, bench/ scripts and scripts/*.sh
    readme = [c for c in COMMANDS if c.file == "README.md"]
    assert [c.text.split("#")[0].strip() for c in readme[:2]] == [
        "bash scripts/main_job.sh",
        "bash scripts/test.sh",
    ]
    assert {"train", "eval", "hub"} <= {c.kind for c in readme}  # the GPU path: fine-tune, evaluate, release


def test_list_values_keep_their_brackets_and_optional_flags_lose_theirs():
    from docs_commands import parse_command

    command = parse_command("docs/x.md", 0, "python train.py [--resume] --data.extra_train_roots=[a,b]")
    assert command.args == ["--resume", "--data.extra_train_roots=[a,b]"]


# -- running the blocks --------------------------------------------------------------------------------
def _executable(command: DocCommand) -> bool:
    key = command.kind if command.kind in ("train", "eval") else f"{command.kind}:{command.sub}"
    historical = (REPO / command.file).is_relative_to(HISTORICAL)
    return command.block is not None and command.runs_on_cpu and key in EXECUTABLE and not historical


def _blocks() -> list:
    blocks: dict[tuple[str, int], list[DocCommand]] = {}
    for command in COMMANDS:
        if _executable(command):
            blocks.setdefault((command.file, command.block), []).append(command)
    params, seen = [], set()
    for (file, _), commands in blocks.items():
        key = tuple(c.text.split("#")[0].strip() for c in commands)
        if key in seen:  # the same command block in several documents runs once
            continue
        seen.add(key)
        marks = [pytest.mark.slow] if any(c.kind == "train" for c in commands) else []
        params.append(pytest.param(commands, id=f"{file}:{commands[0].line}", marks=marks))
    return params


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("docs-data")
    generate_tiny_dataset(root)
    return root


@pytest.fixture(scope="module")
def small_agent(tiny_data, tmp_path_factory) -> Path:
    from eval_helpers import save_small_agent

    from openfly_agent.data.openfly_reader import load_openfly_dataset

    folder = tmp_path_factory.mktemp("docs-agent") / "step-000001"
    save_small_agent(folder, [e.instruction for e in load_openfly_dataset(tiny_data, C.SPLIT_TRAIN)])
    (folder / "train_config.json").write_text(
        json.dumps({"seed": 0, "steps": 1, "init": {"checkpoint": None}})
    )
    return folder


def _value(args: list[str], flag: str) -> str | None:
    for index, arg in enumerate(args):
        if arg == flag and index + 1 < len(args):
            return args[index + 1]
        if arg.startswith(f"{flag}="):
            return arg.split("=", 1)[1]
    return None


def _prepare(command: DocCommand, work: Path, small_agent: Path) -> None:
    """What the command reads and an earlier step would have written (a step that does not run here, such as
    a DAgger round, or an earlier block): a checkpoint run folder, a train root, results."""
    checkpoint = _value(command.args, "--checkpoint")
    if command.kind == "train":
        checkpoint = _value(command.args, "--init.checkpoint")
        roots = (_value(command.args, "--data.extra_train_roots") or "").strip("[]").split(",")
        for index, root in enumerate(roots):
            if root and not (work / root).exists():  # other routes: an episode may be in one root only
                generate_tiny_dataset(work / root, seed=index + 1)
        grounding = _value(command.args, "--data.grounding_root")
        if grounding and not (work / grounding).exists():  # a grounding stage: its referring expressions
            from openfly_agent.toolchain.grounding import generate_grounding

            source = work / (_value(command.args, "--data.root") or DATASET)
            generate_grounding(
                GroundingDataConfig(source_root=str(source), output_dir=str(work / grounding), yaw_copies=0),
                progress=False,
            )
    if checkpoint and command.kind in ("eval", "hub", "train") and not (work / checkpoint).exists():
        run = Path(checkpoint)
        run = run.parent.parent if run.name == "last" else run
        shutil.copytree(small_agent, work / run / "checkpoints" / small_agent.name)
        (work / run / "checkpoints" / "last").write_text(f"{small_agent.name}\n")
    results = _value(command.args, "--results")
    if results and not (work / results).exists():
        overall = {"episodes": 1, "ne_m": 40.0, "sr_pct": 0.0, "osr_pct": 0.0, "spl_pct": 0.0}
        splits = {
            s: {p: {"overall": overall} for p in ("openfly", "standard")}
            for s in (C.SPLIT_TEST_SEEN, C.SPLIT_TEST_UNSEEN)
        }
        path = work / results / "agent" / C.RESULTS_JSON
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"version": 1, "policy": "agent", "splits": splits, "errors": {}}))
        if checkpoint:  # eval.py records the weights it evaluated beside its results; a release checks them
            from openfly_agent.rollout.checkpoints import checkpoint_fingerprint

            identity = {"policy": "agent", "weights": checkpoint_fingerprint(str(work / checkpoint))}
            (path.parent / "run_identity.json").write_text(json.dumps(identity))


def _argv(command: DocCommand) -> list[str]:
    """The documented command as it runs from another folder, with the small-data budget appended."""
    python = [sys.executable]
    launcher = list(command.launcher)
    if launcher[:2] == ["accelerate", "launch"]:
        launcher = [str(Path(sys.executable).with_name("accelerate")), *launcher[1:]]
    elif launcher[:1] == ["torchrun"]:
        launcher = [*python, "-m", "torch.distributed.run", *launcher[1:]]
    elif launcher:
        launcher = [*python, *launcher[1:]]
    launcher = [str(REPO / v) if p == "--config_file" else v for p, v in zip(["", *launcher], launcher)]
    key = command.kind if command.kind in ("train", "eval") else f"{command.kind}:{command.sub}"
    if command.kind in ("train", "eval"):
        target = [str(REPO / command.sub)]
        head = launcher or python
    else:
        module = {
            "toolchain": "openfly_agent.toolchain",
            "hub": "openfly_agent.hub",
            "sim": "openfly_agent.sim.cli",
            "compare": "openfly_agent.eval.compare",
        }
        target, head = ["-m", module[command.kind], *([command.sub] if command.sub else [])], python
    return [*head, *target, *command.args, *BUDGET.get(key, [])]


@pytest.mark.parametrize("commands", _blocks())
def test_documented_command_blocks_run_on_small_data(commands, tiny_data, small_agent, tmp_path):
    work = tmp_path / "work"  # not the repository: configs must be found from anywhere, outputs land here
    work.mkdir()
    if not any(c.sub == "generate" for c in commands):
        shutil.copytree(tiny_data, work / DATASET)
    env = {k: v for k, v in os.environ.items() if not k.startswith("HF_")}
    env.update(HF_HUB_OFFLINE="1", HF_DATASETS_OFFLINE="1", TRANSFORMERS_OFFLINE="1", PYTHONPATH=str(REPO))
    env.update(TOKENIZERS_PARALLELISM="false", OMP_NUM_THREADS="1", HF_HOME=str(tmp_path / "hf"))
    for command in commands:
        _prepare(command, work, small_agent)
        if command.kind == "train" and "--resume" not in " ".join(command.args):
            # Training commands of one block are alternatives ("or: python train.py") unless they resume.
            output_dir = _load("train").parse_args([*command.args, *BUDGET["train"]]).output_dir
            shutil.rmtree(work / output_dir, ignore_errors=True)
        done = run_group(_argv(command), timeout=600, cwd=work, env={**env, **command.env})
        assert done.returncode == 0, f"{command.where}\n{done.stdout[-2000:]}\n{done.stderr[-4000:]}"


# -- Python snippets -----------------------------------------------------------------------------------
NEEDS_MORE = ("my-user/", "AirSimBridge", "from datasets import")  # the Hub, a running engine


def _check_imports(snippet: DocSnippet) -> None:
    tree = ast.parse(snippet.code)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            module = importlib.import_module(node.module)
            for alias in node.names:
                assert hasattr(module, alias.name) or importlib.util.find_spec(
                    f"{node.module}.{alias.name}"
                ), f"{snippet.where}: {node.module} has no {alias.name}"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                importlib.import_module(alias.name)


@pytest.mark.parametrize("snippet", SNIPPETS, ids=lambda s: s.where)
def test_documented_python_snippets(snippet, tmp_path, monkeypatch):
    _check_imports(snippet)
    if any(word in snippet.code for word in NEEDS_MORE):
        return
    monkeypatch.chdir(tmp_path)
    exec(compile(snippet.code, snippet.where, "exec"), {"__name__": "__doc_snippet__"})


# -- paths and names in prose --------------------------------------------------------------------------
# Every inline code span of README.md, docs/*.md and data_cards/*.md that names a file of the repository or a
# name of its code must resolve against the tree (fenced blocks are commands and snippets, checked above).
# The experiment log (docs/experiments/) is exempt: its dated entries record what the code was then, and may
# rightly name files and functions deleted since (its commands' options are still checked, above).
#
# A path: a span of path characters that contains "/" and starts with an entry of the repository root
# (`configs/train/tiny.yaml`, `docs/TRAINING.md`), a package part's folder (`model/`), or any path or bare file
# name ending in .py or .sh (`model/agent.py`, `vision/backbone.py`, `agent.py`: a file whose path ends so);
# `path.py::Name` also needs Name defined in that file. Not paths: `outputs/`, `runs/`, placeholders (`<dir>`,
# `...`), and the files of a dataset, run or checkpoint (`meta/info.json`, `config.json`).
# A name: a dotted identifier or a call, `openfly_agent.eval.compare`, `train()`, `agent.forward`,
# `OpenFlyAgent.new_session`, `model.grounding.attribute_weight`. `openfly_agent.<module>[.<name>]`
# must be a module of the package and a name it defines; otherwise the last part must be a function, class,
# method, field or attribute the code defines (an ast scan of openfly_agent/, bench/, scripts/ and the entry
# points), and `Class.member` a member of that class. Plain words (`tiny`, `discrete`) are not checked.
PROSE_DOCS = [REPO / "README.md", *sorted(REPO.glob("docs/*.md")), *sorted(REPO.glob("data_cards/*.md"))]
CODE_ROOTS = ("openfly_agent", "bench", "scripts", "train.py", "eval.py")
NOT_IN_TREE = {  # named on purpose, never files of this repository
    "train/eval.py": "the released OpenFly code's files (docs/OFFICIAL_OPENFLY.md)",
    "train/dataset_builder/vln/vln_dataset_builder.py": "the released OpenFly code's files",
    "configs/eval_test.json": "the released OpenFly code's files",
    "configs/env_*.yaml": "the released OpenFly code's files",
    "_meta_registrations.py": "torch's own file (docs/INSTALL.md, a torchvision fix)",
    "configuration_openfly_agent.py": "written into each checkpoint (model/persistence/remote_code.py)",
    "modeling_openfly_agent.py": "written into each checkpoint",
    "processing_openfly_agent.py": "written into each checkpoint",
}
FOREIGN = {  # first part of a name -> why it is not this package's
    "torch": "PyTorch", "np": "NumPy", "numpy": "NumPy", "math": "the standard library", "sys": "the standard library",
    "transformers": "transformers", "huggingface_hub": "huggingface_hub", "cv2": "OpenCV",
    "accelerator": "accelerate's Accelerator", "Accelerator": "accelerate", "ops": "torchvision.ops",
    "ls1": "timm's LayerScale keys", "LayerNorm": "timm / transformers key names",
    "vit_large_patch14_reg4_dinov2": "a timm model name", "destroy_process_group": "torch.distributed",
    "enableApiControl": "AirSim's client", "armDisarm": "AirSim's client",
}  # fmt: skip
# Members a class of ours inherits from transformers (`OpenFlyProcessor.from_pretrained`)
INHERITED = {
    "from_pretrained",
    "save_pretrained",
    "push_to_hub",
    "load_state_dict",
    "state_dict",
}  # torch / transformers
FILE_SUFFIXES = {  # a span ending so is a file name (`config.json`), not code
    "json", "jsonl", "safetensors", "parquet", "png", "md", "txt", "ini", "so", "yaml", "yml", "toml",
}  # fmt: skip
_FENCE = re.compile(r"^\s*(```|~~~)")
_PATH = re.compile(r"[\w.\-/*]+")
_NAME = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*(\((\w+(, \w+)*)?\))?")


@dataclasses.dataclass(frozen=True)
class CodeIndex:
    """What prose may name: the files and folders of the tree and the names its Python code defines."""

    paths: tuple[str, ...]  # files and folders, relative to the repository
    names: frozenset[str]  # functions, classes, methods, fields, attributes, module names
    members: dict  # class name -> the names defined in its body (methods, fields, self.<attribute>)
    modules: dict  # dotted module of the package -> its top-level names (with a lazy package's exports)


def _targets(node: ast.AST) -> list[str]:
    """The names an assignment target binds: `x`, `self.x`, `a, b`."""
    if isinstance(node, ast.Name):
        return [node.id]
    if isinstance(node, ast.Attribute):
        return [node.attr]
    if isinstance(node, (ast.Tuple, ast.List)):
        return [name for element in node.elts for name in _targets(element)]
    return []


def _bound(node: ast.AST) -> list[str]:
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return [node.name]
    if isinstance(node, ast.Assign):
        return [name for target in node.targets for name in _targets(target)]
    if isinstance(node, ast.AnnAssign):
        return _targets(node.target)
    if isinstance(node, (ast.Import, ast.ImportFrom)):
        return [(alias.asname or alias.name).split(".")[0] for alias in node.names]
    return []


def _tree_paths() -> tuple[str, ...]:
    skip = {".git", ".venv", "outputs", "runs", "__pycache__", ".hypothesis", ".ruff_cache", ".pytest_cache"}
    paths, folders = [], [REPO]
    while folders:
        for path in folders.pop().iterdir():
            if path.name not in skip and not path.name.endswith(".egg-info"):
                paths.append(path.relative_to(REPO).as_posix())
                if path.is_dir():
                    folders.append(path)
    return tuple(paths)


@functools.cache
def code_index() -> CodeIndex:
    paths = _tree_paths()
    names, members, modules = set(), {}, {}
    for rel in paths:
        if not rel.endswith(".py") or not rel.startswith(CODE_ROOTS):
            continue
        tree = ast.parse((REPO / rel).read_text())
        names.add(Path(rel).stem)
        module = rel.removesuffix(".py").removesuffix("/__init__").replace("/", ".")
        top = {name for node in tree.body for name in _bound(node)}
        exports = tree.body if rel.endswith("__init__.py") else []  # a package's lazy exports: name -> module
        for node in exports:
            if isinstance(node, ast.Assign) and isinstance(node.value, ast.Dict):
                top |= {key.value for key in node.value.keys if isinstance(key, ast.Constant)}
        modules[module] = top
        _collect(tree, None, names, members)
    return CodeIndex(paths, frozenset(names), members, modules)


def _collect(node: ast.AST, owner: str | None, names: set, members: dict) -> None:
    """Every name bound under `node` into `names`, and into `members[owner]` inside class `owner`'s body."""
    for child in ast.iter_child_nodes(node):
        bound = _bound(child)
        names.update(bound)
        if owner is not None:
            members[owner].update(bound)
        if isinstance(child, ast.ClassDef):
            members.setdefault(child.name, set())
        _collect(child, child.name if isinstance(child, ast.ClassDef) else owner, names, members)


def _path_resolves(path: str, index: CodeIndex) -> bool:
    if path in NOT_IN_TREE:
        return True
    path = path.rstrip("/")
    if path.split("/")[0] in {p for p in index.paths if "/" not in p}:
        return any(fnmatch.fnmatchcase(p, path) for p in index.paths)
    return any(fnmatch.fnmatchcase(p, path) or fnmatch.fnmatchcase(p, f"*/{path}") for p in index.paths)


def _defines(path: str, name: str, index: CodeIndex) -> bool:
    """Whether the file `path` (as `_path_resolves` finds it) defines `name` anywhere in it."""
    files = [p for p in index.paths if p == path or p.endswith(f"/{path}")]
    trees = [ast.parse((REPO / file).read_text()) for file in files]
    return any(name in _bound(node) for tree in trees for node in ast.walk(tree))


def _is_repo_path(span: str, index: CodeIndex) -> bool:
    if not _PATH.fullmatch(span) or span.startswith(("outputs/", "runs/")):
        return False
    first = span.split("/")[0]
    if "/" in span and first in {p for p in index.paths if "/" not in p}:
        return True
    if span.endswith("/") and f"openfly_agent/{first}" in index.paths:
        return True
    return re.search(r"(^|/)[\w*-]+\.(py|sh)$", span) is not None


def _name_resolves(span: str, index: CodeIndex) -> bool:
    parts = span.split("(")[0].split(".")
    if parts[0] in FOREIGN or parts[0] in dir(builtins):
        return True
    if parts[0] == "openfly_agent":
        cut = max((k for k in range(1, len(parts) + 1) if ".".join(parts[:k]) in index.modules), default=0)
        rest = parts[cut:]
        return cut > 0 and (not rest or rest[0] in index.modules[".".join(parts[:cut])])
    if parts[-1] not in index.names:
        return parts[-1] in INHERITED  # `agent.load_state_dict`: torch's / transformers' method of our class
    owner = parts[0] if len(parts) > 1 and parts[0][:1].isupper() else None
    return owner not in index.members or parts[1] in index.members[owner] | INHERITED


def prose_reference_misses(path: Path, text: str | None = None) -> tuple[list[str], int]:
    """(`file:line: span` of each path or name that does not resolve, how many spans were checked)."""
    index, misses, checked, inside = code_index(), [], 0, False
    relative = path.relative_to(REPO).as_posix() if path.is_relative_to(REPO) else str(path)
    for number, line in enumerate((path.read_text() if text is None else text).splitlines(), 1):
        if _FENCE.match(line):
            inside = not inside
        if inside or _FENCE.match(line):
            continue
        for span in (m.group(1).strip() for m in re.finditer(r"`([^`]+)`", line)):
            if "..." in span or "<" in span:
                continue
            if re.fullmatch(r"[\w./*-]+\.py::[\w.]+", span):
                file, name = span.split("::")
                ok = _path_resolves(file, index) and _defines(file, name.split(".")[0], index)
            elif _is_repo_path(span, index):
                ok = _path_resolves(span, index)
            elif _NAME.fullmatch(span) and ("." in span or "(" in span):
                if span.rsplit(".", 1)[-1] in FILE_SUFFIXES:
                    continue
                ok = _name_resolves(span, index)
            else:
                continue
            checked += 1
            if not ok:
                misses.append(f"{relative}:{number}: `{span}`")
    return misses, checked


def test_every_backticked_path_and_name_in_the_docs_resolves():
    misses, checked = [], 0
    for doc in PROSE_DOCS:
        found, count = prose_reference_misses(doc)
        misses += found
        checked += count
    assert checked > 500 and not misses, "\n".join(misses)


def test_a_stale_path_or_name_is_caught():
    prose = (
        "`conv_vision.py` `openfly_agent/model/agent.py` `configs/train/nope.yaml` `configs/train/tiny.yaml`\n"
        "`activation_checkpointing_enable()` `train()` `OpenFlyAgent.nope` `OpenFlyAgent.forward`\n"
        "`openfly_agent.eval.nope` `openfly_agent.eval.compare` `model/nope.py::f` `data/labels.py::Episode`\n"
        "```bash\n`not_checked_in_a_block()`\n```\n`torch.compile` `outputs/x/y.py` `<dir>/x.py` `meta/info.json`\n"
    )
    misses, checked = prose_reference_misses(REPO / "docs" / "x.md", prose)
    assert [m.split(": ", 1)[1] for m in misses] == [
        "`conv_vision.py`", "`configs/train/nope.yaml`", "`activation_checkpointing_enable()`",
        "`OpenFlyAgent.nope`", "`openfly_agent.eval.nope`", "`model/nope.py::f`",
    ]  # fmt: skip
    assert checked == 13  # the block, the placeholders and the dataset file are not checked
