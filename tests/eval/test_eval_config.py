"""EvalConfig parsing (draccus' dotted options, as every entry point) and its errors."""

from __future__ import annotations

import pytest

from openfly_agent.eval.config import AgentSettings, AirSimSimSettings, EvalConfig
from openfly_agent.utils.cli_options import CommandLineError, UnknownOptionError
from openfly_agent.utils.config import parse_config


def _eval_main():
    """`main` of the repository's eval.py (a script, not a module of the package)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "eval.py"
    spec = importlib.util.spec_from_file_location("eval_entry_point", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main


def test_the_documented_command_line_parses():
    argv = [
        "--checkpoint=runs/tiny/checkpoints/last",
        "--split=[test_seen,test_unseen]",
        "--sim.type=embedded",
    ]
    cfg = parse_config(EvalConfig, argv)
    assert cfg.split == ["test_seen", "test_unseen"] and cfg.sim.type == "embedded"
    assert cfg.checkpoint == "runs/tiny/checkpoints/last" and cfg.policy == "agent"
    argv = [
        "--split",
        "[test_unseen]",
        "--sim.type",
        "unrealcv",
        "--sim.unrealcv.port=9001",
        "--baselines=[random,stop]",
    ]
    cfg = parse_config(EvalConfig, [*argv, "--gif_episodes=[a/b/c]", "--checkpoint=x"])
    assert (
        cfg.baselines == ["random", "stop"] and cfg.split == ["test_unseen"] and cfg.gif_episodes == ["a/b/c"]
    )
    assert cfg.sim.type == "unrealcv" and cfg.sim.unrealcv.port == 9001


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["--split", "test_seen", "test_unseen"],
            "--split takes one value, 'test_unseen' is a second one: write a list as --split=[a,b]",
        ),
        (
            ["--sim", "embedded"],
            "--sim is a section: set its fields (--sim.type=embedded) or give it a YAML file",
        ),
        (["--sim=airsim"], "--sim is a section: set its fields (--sim.type=airsim)"),
        (["stop"], "unexpected value 'stop': every value follows its --option"),
    ],
)
def test_a_second_value_or_a_value_of_a_section_is_one_line_naming_the_option(argv, message):
    with pytest.raises(UnknownOptionError) as err:
        parse_config(EvalConfig, ["--policy=oracle", *argv] if argv[0].startswith("--") else argv)
    assert message in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("yaml_text", "message"),
    [
        (
            "sim:\n  type: habitat\n",
            "--sim.type: unknown choice 'habitat'; choose one of embedded, unrealcv, airsim, gs_http",
        ),
        ("sim: [\n", "--config_path {path}: not valid YAML (while parsing a flow node"),
    ],
)
def test_a_config_file_with_no_such_choice_or_broken_yaml_is_one_line(yaml_text, message, tmp_path):
    path = tmp_path / "eval.yaml"
    path.write_text(yaml_text)
    with pytest.raises(CommandLineError) as err:
        parse_config(EvalConfig, ["--policy=oracle", "--config_path", str(path)])
    assert message.format(path=path) in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"policy": "agent"}, "needs --checkpoint"),
        ({"policy": "random", "baselines": ["agent_true_box"]}, "'agent_true_box' needs --checkpoint"),
        (
            {
                "policy": "agent",
                "checkpoint": "c",
                "baselines": ["agent_true_box"],
                "sim": AirSimSimSettings(),
            },
            "agent_true_box reads the true target box",
        ),
        ({"policy": "greedy"}, "choose from"),
        ({"policy": "random", "baselines": ["random"]}, "must not repeat"),
        ({"policy": "stop", "split": ["validation"]}, "split 'validation'"),
        ({"policy": "stop", "profiles": ["habitat"]}, "profile 'habitat'"),
        ({"policy": "stop", "batch_size": 0}, "batch_size"),
        ({"policy": "stop", "oracle_mode": "fly"}, "oracle_mode"),
        ({"policy": "stop", "true_box": "next"}, "true_box='next': choose from"),
        ({"policy": "stop", "true_box": "leg"}, "true_box=leg feeds agent_true_box .* add agent_true_box"),
        (
            {
                "policy": "agent",
                "checkpoint": "c",
                "baselines": ["agent_true_box", "box_servo"],
                "true_box": "leg",
            },
            "leave box_servo out",
        ),
    ],
)
def test_config_errors_say_what_to_change(kwargs, message):
    with pytest.raises(ValueError, match=message):
        EvalConfig(**kwargs)


def test_result_identity_tracks_what_changes_results():
    a = EvalConfig(policy="random", seed=1)
    b = EvalConfig(policy="random", seed=2, batch_size=64, plots=0)
    assert a.result_identity("random") != b.result_identity("random")
    assert a.result_identity("stop") == b.result_identity("stop")  # batch size and plots never change results
    c, d = (EvalConfig(policy="agent", checkpoint=name, baselines=["agent_true_box"]) for name in ("c", "d"))
    assert c.result_identity("agent_true_box") != d.result_identity("agent_true_box")  # its weights
    assert c.result_identity("agent_true_box") != c.result_identity("agent")  # never resumes the agent's log
    leg = EvalConfig(policy="agent", checkpoint="c", baselines=["agent_true_box"], true_box="leg")
    assert leg.result_identity("agent_true_box") == {**c.result_identity("agent_true_box"), "true_box": "leg"}
    assert leg.result_identity("agent") == c.result_identity("agent")  # the agent reads no true box
    assert "true_box" not in c.result_identity("agent_true_box")  # absent: the final target, as older logs


@pytest.mark.parametrize(
    "name", ["embedded", "baselines", "released-unrealcv", "released-airsim", "released-gs"]
)
def test_shipped_configs_parse(name):
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "configs" / "eval" / f"{name}.yaml"
    cfg = parse_config(EvalConfig, ["--config_path", str(path), "--checkpoint=ckpt"])
    assert cfg.sim.type in ("embedded", "unrealcv", "airsim", "gs_http")
    if name.startswith("released"):
        assert cfg.agent.unnorm_key == "vlnv1" and cfg.agent.decode_rule == "exact" and cfg.batch_size == 1
        assert cfg.reader.takeoff_landing == "keep"


def test_one_torch_thread_by_default_and_the_flag_still_chooses():
    """torch's default (a thread per core) thrashed on a shared 2-core machine: 153 s of policy time against
    7.5 s with one thread for the same 2 episodes (docs/EVAL.md, "Throughput")."""
    assert parse_config(EvalConfig, ["--policy=random"]).torch_threads == 1
    assert parse_config(EvalConfig, ["--policy=random", "--torch_threads=4"]).torch_threads == 4
    assert parse_config(EvalConfig, ["--policy=random", "--torch_threads=null"]).torch_threads is None


def test_an_in_process_evaluation_leaves_the_callers_thread_count(tmp_path):
    """eval.py sets `torch_threads` for its process; the library's run() leaves the count alone, so a test or a
    notebook that evaluates in-process keeps its own. Torch numerics depend on it beyond the count itself: after
    any `torch.set_num_threads` (even back to the same count) an in-process training no longer matched a fresh
    process bit for bit, so this test asks for another count and never sets one itself."""
    import torch

    from openfly_agent.eval.run import run

    before = torch.get_num_threads()
    cfg = parse_config(
        EvalConfig,
        ["--policy=random", f"--torch_threads={before + 1}", f"--dataset_root={tmp_path / 'none'}"],
    )
    with pytest.raises(FileNotFoundError):  # no dataset there
        run(cfg)
    assert torch.get_num_threads() == before


@pytest.mark.parametrize(
    ("argv", "cls", "section"),
    [
        ([], "EmbeddedSimSettings", None),
        (["--sim.type=embedded", "--sim.width=64"], "EmbeddedSimSettings", None),
        (["--sim.type=unrealcv", "--sim.unrealcv.host=10.0.0.2"], "UnrealCVSimSettings", "unrealcv"),
        (["--sim.type=airsim", "--sim.occupancy_pcd=pcd/{scene_id}.pcd"], "AirSimSimSettings", "airsim"),
        (["--sim.type=gs_http", "--sim.port_per_rank=false"], "GSHttpSimSettings", "gs_http"),
    ],
)
def test_each_sim_type_builds_its_variant_with_only_its_fields(argv, cls, section):
    from openfly_agent.eval.config import BridgeSimSettings

    sim = parse_config(EvalConfig, ["--policy=random", *argv]).sim
    assert type(sim).__name__ == cls and sim.type == (section or "embedded")
    assert isinstance(sim, BridgeSimSettings) == (section is not None)
    assert hasattr(sim, "width") == (section is None)  # the embedded frame size only on the embedded sim
    for other in ("unrealcv", "airsim", "gs_http"):  # a bridge's section only on its own variant
        assert hasattr(sim, other) == (other == section)
    if section is not None:
        assert sim.bridge_config() is getattr(sim, section)


def test_the_embedded_identity_keeps_its_keys():
    """Logs written before the simulator became a choice resume: the embedded identity is unchanged."""
    identity = parse_config(EvalConfig, ["--policy=random", "--sim.width=64"]).result_identity("random")
    assert {k: v for k, v in identity.items() if k.startswith("sim_")} == {
        "sim_type": "embedded",
        "sim_width": 64,
        "sim_height": None,
        "sim_occupancy": None,
    }


def test_a_bridge_field_on_the_embedded_sim_is_one_line_naming_the_option(capsys):
    main = _eval_main()
    assert main(["--policy=random", "--sim.occupancy_pcd=pcd/{scene_id}.pcd"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--sim" in err and "occupancy_pcd" in err and "EmbeddedSimSettings" in err
    assert main(["--policy=random", "--sim.type=airsim", "--sim.unrealcv.port=9001"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "unrealcv" in err and "AirSimSimSettings" in err


def test_help_shows_the_chosen_sims_fields_only(capsys):
    main = _eval_main()
    assert main(["--sim.type=airsim", "--help"]) == 0
    text = capsys.readouterr().out
    assert "--sim.airsim.port" in text and "--sim.occupancy_pcd" in text
    assert "--sim.unrealcv." not in text and "--sim.gs_http." not in text and "--sim.width" not in text
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "--sim.width" in text and "--sim.airsim." not in text and "--sim.occupancy_pcd" not in text


def test_memory_probe_is_recorded_and_never_resumes_another_probe(tmp_path):
    from openfly_agent.eval.distributed import ProcessInfo
    from openfly_agent.eval.outputs import run_meta
    from openfly_agent.eval.run import prepare_output

    trained = parse_config(EvalConfig, ["--checkpoint=c"])
    probe = parse_config(EvalConfig, ["--checkpoint=c", "--agent.memory_probe=empty"])
    assert trained.agent.memory_probe == "none"
    # older run_identity.json files have no such key: the default adds none, so they still resume
    assert "memory_probe" not in trained.result_identity("agent")
    assert probe.result_identity("agent")["memory_probe"] == "empty"
    assert "memory_probe" not in probe.result_identity("random")  # baselines have no memory
    assert (
        run_meta(probe, "agent")["memory_probe"] == "empty"
        and run_meta(probe, "random")["memory_probe"] is None
    )
    folder = tmp_path / "agent"
    prepare_output(folder, probe.result_identity("agent"), False, ProcessInfo())
    with pytest.raises(ValueError, match="memory_probe: 'empty' -> None"):  # a key only the folder has
        prepare_output(folder, trained.result_identity("agent"), False, ProcessInfo())
    with pytest.raises(ValueError, match="agent.memory_probe='swap': choose one of"):
        EvalConfig(checkpoint="c", agent=AgentSettings(memory_probe="swap"))
