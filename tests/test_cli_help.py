"""`--help` of every entry point: exit 0 on stdout, each flag with its description and the default a plain run
uses, and an example at the end. Unknown options get a one-line "did you mean" instead of a usage dump."""

from __future__ import annotations

import contextlib
import importlib.util
import re
import sys
from pathlib import Path

import pytest

from openfly_agent.utils.processes import run_group

REPO = Path(__file__).resolve().parents[1]


def _script_main(name: str):
    spec = importlib.util.spec_from_file_location(f"{name}_entry_point", REPO / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main


def _toolchain(argv):
    from openfly_agent.toolchain.__main__ import main

    return main(argv)


def _hub(argv):
    from openfly_agent.hub.cli import main

    return main(argv)


def _sim(argv):
    from openfly_agent.sim.cli import main

    return main(argv)


def _help(capsys, main, argv) -> str:
    """stdout of `main(argv)`, which must succeed (return 0 / None, or argparse's SystemExit(0))."""
    code = 0
    try:
        code = main(argv) or 0
    except SystemExit as done:
        code = done.code or 0
    out, err = capsys.readouterr()
    assert code == 0 and out.strip(), err[-2000:]
    return out


def flag_text(text: str, flag: str) -> str:
    """The help of `flag`: its line and the indented lines that continue it, on one line."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if re.match(rf"^\s+{re.escape(flag)}(\s|$|,)", line))
    block = [lines[start]]
    for line in lines[start + 1 :]:
        if not line.startswith("   ") or line.lstrip().startswith("-"):
            break
        block.append(line)
    return " ".join(" ".join(block).split())


def ends_with_example(text: str, program: str) -> bool:
    lines = [line for line in text.splitlines() if line.strip()]
    return "example" in "\n".join(lines[-12:]) and program in lines[-1]


def test_train_help_shows_what_a_plain_run_uses(capsys):
    text = _help(capsys, _script_main("train"), ["--help"])
    steps = flag_text(text, "--steps")
    assert "optimizer steps of the run" in steps and "(default: 1500)" in steps  # configs/train/tiny.yaml
    assert "(default: 0.001)" in flag_text(text, "--optim.lr")  # tiny.yaml's 1.0e-3, not the dataclass' 3e-4
    assert "(default: outputs/train/tiny)" in flag_text(text, "--output_dir")
    assert "working directory" in flag_text(text, "--output_dir")
    assert "(default: 250)" in flag_text(text, "--checkpoint.save_interval")
    assert ends_with_example(text, "train.py")
    intro = " ".join(text.split())  # train.py reads a dataset, never makes one (the toolchain does)
    assert "generated first when missing" not in intro
    assert "python -m openfly_agent.toolchain generate" in intro
    overridden = _help(capsys, _script_main("train"), ["--steps=7", "--help"])  # the command line's values
    assert "(default: 7)" in flag_text(overridden, "--steps")


def test_train_unknown_option_says_did_you_mean(capsys):
    assert _script_main("train")(["--optim.lrr=1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "train.py: unknown option --optim.lrr; did you mean --optim.lr? (--help lists every option)"
    ]


def test_eval_help_attaches_each_description_to_its_flag(capsys):
    text = _help(capsys, _script_main("eval"), ["--help"])
    assert "checkpoint folder" in flag_text(text, "--checkpoint")
    assert "more policies" in flag_text(text, "--baselines") and "checkpoint" not in flag_text(
        text, "--baselines"
    )
    assert "random baseline" in flag_text(text, "--seed") and "GIF" not in flag_text(text, "--seed")
    assert "GIF" in flag_text(text, "--gif_episodes")
    assert "(default: [test_seen,test_unseen])" in flag_text(text, "--split") and "splits" in flag_text(
        text, "--split"
    )
    assert "(default: outputs/eval)" in flag_text(text, "--output_dir") and "summary.md" in flag_text(
        text, "--output_dir"
    )
    # a bridge's fields appear when the sim is that bridge
    unrealcv = _help(capsys, _script_main("eval"), ["--sim.type=unrealcv", "--help"])
    assert "(default: 9000)" not in unrealcv and "TCP port" in flag_text(unrealcv, "--sim.unrealcv.port")
    assert "(default: 16)" in flag_text(text, "--batch_size")
    assert ends_with_example(text, "eval.py")
    preset = _help(
        capsys, _script_main("eval"), ["--config_path", "configs/eval/released-unrealcv.yaml", "--help"]
    )
    assert "\nsim: `unrealcv` (--sim.type=unrealcv; other variants: embedded," in preset
    assert _script_main("eval")(["--sim.type=unrealcv", "--sim.unrealcv.prot=1"]) == 2
    assert "did you mean --sim.unrealcv.port?" in capsys.readouterr().err


def test_toolchain_help_exits_0_on_stdout():
    done = run_group([sys.executable, "-m", "openfly_agent.toolchain", "--help"], timeout=120, cwd=REPO)
    assert done.returncode == 0 and done.stderr == ""
    for command in ("generate", "summarize", "dagger", "segment"):
        assert f"  {command} " in done.stdout
    assert ends_with_example(done.stdout, "openfly_agent.toolchain")
    bare = run_group([sys.executable, "-m", "openfly_agent.toolchain"], timeout=120, cwd=REPO)
    assert bare.returncode == 2 and bare.stderr.count("\n") == 1 and "no command given" in bare.stderr


def test_toolchain_subcommand_helps(capsys):
    text = _help(capsys, _toolchain, ["generate", "--help"])  # crashed on a bare % in a field comment
    assert "(default: 128)" in flag_text(text, "--render.width")
    assert "weighted A*" in flag_text(text, "--planner.heuristic_weight")
    assert "generate anew" in flag_text(text, "--overwrite")
    assert ends_with_example(text, "openfly_agent.toolchain generate")
    preset = _help(
        capsys, _toolchain, ["generate", "--config_path", "configs/toolchain/embedded-small.yaml", "--help"]
    )
    assert "(default: 130)" in flag_text(preset, "--scenes.trajectories_per_scene")
    dagger = _help(capsys, _toolchain, ["dagger", "--help"])  # demanded --checkpoint instead
    assert "trained agent" in flag_text(dagger, "--checkpoint STR") and "--dagger.noise_prob" in dagger
    assert ends_with_example(dagger, "openfly_agent.toolchain dagger")
    for command, flag in (("summarize", "--root"), ("segment", "--point_cloud")):
        text = _help(capsys, _toolchain, [command, "--help"])
        assert flag in text and ends_with_example(text, f"openfly_agent.toolchain {command}")
    assert _toolchain(["generate", "--render.widht=96"]) == 2
    assert "did you mean --render.width?" in capsys.readouterr().err


def test_hub_helps(capsys):
    text = _help(capsys, _hub, ["release", "--help"])
    assert "(default: merged)" in flag_text(text, "--lora") and "adapter" in flag_text(text, "--lora")
    assert "(default: 5GB)" in flag_text(text, "--max_shard_size")
    assert ends_with_example(text, "openfly_agent.hub release")
    dataset = _help(capsys, _hub, ["release-dataset", "--help"])
    assert "(default: data_cards/embedded.md)" in flag_text(dataset, "--card")
    assert ends_with_example(dataset, "openfly_agent.hub release-dataset")
    fake = _help(capsys, _hub, ["fake-hub", "--help"])
    assert "HF_TOKEN" in flag_text(fake, "--token") and ends_with_example(fake, "fake-hub")
    assert ends_with_example(_help(capsys, _hub, ["--help"]), "openfly_agent.hub")


def test_sim_cli_helps(capsys):
    text = _help(capsys, _sim, ["render", "--help"])
    assert "(default: [0.0,0.0,60.0,0.0])" in flag_text(text, "--pose") and "yaw" in flag_text(text, "--pose")
    assert "(default: 1000.0)" in flag_text(text, "--size_m")
    assert "(default: 224)" in flag_text(text, "--width") and "pixels" in flag_text(text, "--width")
    assert "negative = down" in flag_text(text, "--pitch")
    assert ends_with_example(text, "openfly_agent.sim.cli render")
    assert ends_with_example(_help(capsys, _sim, ["--help"]), "openfly_agent.sim.cli")
    export = _help(capsys, _sim, ["export", "--help"])
    assert "(default: 2.0)" in flag_text(export, "--spacing")


@pytest.mark.parametrize("argv", [["--foo"], ["--steps=1", "--stepz=2"]])
def test_unknown_options_never_dump_the_usage(capsys, argv):
    with contextlib.suppress(SystemExit):
        assert _script_main("train")(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "usage" not in err


def test_the_usage_of_a_command_line_with_sub_commands():
    from openfly_agent.utils.cli_help import commands_usage

    text = commands_usage(
        "prog", "What it does.", {"a": "first", "bb": "second"}, ["prog a --x=1", "prog bb"], name_width=3
    )
    assert text == (
        "usage: prog {a,bb} [--<field>=VALUE ...]   (<command> --help for its options)\n"
        "\n"
        "What it does.\n"
        "\n"
        "commands:\n"
        "  a   first\n"
        "  bb  second\n"
        "\n"
        "examples:\n"
        "  prog a --x=1\n"
        "  prog bb\n"
    )
    assert commands_usage("p", "s", {"c": "t"}, [], options="[options]").startswith(
        "usage: p {c} [options]   ("
    )
