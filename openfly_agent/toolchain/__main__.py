"""Command line of the data toolchain.

    python -m openfly_agent.toolchain generate --config configs/toolchain/embedded-small.yaml [--shard 0/4]
    python -m openfly_agent.toolchain summarize --root outputs/datasets/embedded-small
    python -m openfly_agent.toolchain dagger --config <yaml> --checkpoint DIR [--dagger.episodes_per_scene=4]
    python -m openfly_agent.toolchain segment --env_yaml env_x.yaml --point_cloud x.pcd --out seg_map_x.jsonl
    python -m openfly_agent.toolchain grounding --source_root outputs/datasets/embedded-small \
        --output_dir outputs/datasets/grounding-small

`generate` / `dagger` take every GenerateConfig field as a dotted override (`--render.width=96`).
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path

from openfly_agent.utils.logging_utils import setup_logging

COMMANDS = ("generate", "summarize", "dagger", "segment", "grounding")


def _config_args(args: list[str]) -> list[str]:
    """Accept `--config X` / `--config=X` as draccus' `--config_path`."""
    out = []
    for arg in args:
        if arg == "--config":
            arg = "--config_path"
        elif arg.startswith("--config="):
            arg = "--config_path=" + arg.split("=", 1)[1]
        out.append(arg)
    return out


def _parse_generate(args: list[str]):
    """GenerateConfig from YAML + overrides; a bad value exits with the message that names the field."""
    import draccus

    from openfly_agent.toolchain.config import GenerateConfig
    from openfly_agent.utils.config import parse_config

    try:
        return parse_config(GenerateConfig, _config_args(args))
    except draccus.utils.ParsingError as err:
        cause = err.__cause__
        while cause is not None and cause.__cause__ is not None and not isinstance(cause, ValueError):
            cause = cause.__cause__
        raise SystemExit(f"bad generate config: {cause or err}") from None


def cmd_generate(args: list[str]) -> None:
    from openfly_agent.toolchain.generate import generate

    summary = generate(_parse_generate(args))
    print(json.dumps({k: summary[k] for k in ("trajectories", "per_split", "rejected", "vocabulary_size")}))


def cmd_summarize(args: list[str]) -> None:
    from openfly_agent.data.writer import OpenFlyDatasetWriter
    from openfly_agent.toolchain.summary import write_summary

    parser = argparse.ArgumentParser(prog="openfly-generate summarize", description="merge shards, summarise")
    parser.add_argument("--root", required=True, help="dataset root holding one or more copied shards")
    parser.add_argument("--no-plots", action="store_true")
    ns = parser.parse_args(args)
    OpenFlyDatasetWriter(ns.root).finalize()
    print(json.dumps(write_summary(ns.root, plots=not ns.no_plots), indent=2))


def load_agent(checkpoint: str, agent_class: str):
    """`module:Class` with a `from_pretrained(path)` classmethod (default: the OpenFlyAgent)."""
    module_name, _, class_name = agent_class.partition(":")
    try:
        cls = getattr(importlib.import_module(module_name), class_name)
    except (ImportError, AttributeError) as err:
        raise SystemExit(f"--agent_class {agent_class!r} cannot be imported: {err}") from None
    return cls.from_pretrained(checkpoint)


def cmd_dagger(args: list[str]) -> None:
    from openfly_agent.toolchain.dagger import AgentPolicy
    from openfly_agent.toolchain.generate import generate
    from openfly_agent.toolchain.pipeline import KIND_DAGGER_POLICY

    parser = argparse.ArgumentParser(prog="openfly-generate dagger", add_help=False)
    parser.add_argument("--checkpoint", required=True, help="trained agent folder (or Hub id)")
    parser.add_argument("--agent_class", default="openfly_agent.model.agent:OpenFlyAgent")
    ns, rest = parser.parse_known_args(args)
    cfg = _parse_generate(rest)
    policy = AgentPolicy(load_agent(ns.checkpoint, ns.agent_class))
    summary = generate(cfg, policy=policy, kinds=(KIND_DAGGER_POLICY,))
    print(json.dumps({k: summary[k] for k in ("trajectories", "dagger_episodes", "rejected")}))


def cmd_segment(args: list[str]) -> None:
    from openfly_agent.toolchain.landmarks import write_landmark_list
    from openfly_agent.toolchain.pipeline import prepare_scene
    from openfly_agent.toolchain.scenes import generate_config_for_real_scene, real_scene

    parser = argparse.ArgumentParser(prog="openfly-generate segment", description="BEV landmark segmentation")
    parser.add_argument("--env_yaml", required=True)
    parser.add_argument("--point_cloud", required=True, help=".pcd (ASCII or binary) or .ply")
    parser.add_argument("--out", required=True, help="landmark list to write (official seg_map JSONL)")
    ns = parser.parse_args(args)
    cfg = generate_config_for_real_scene(ns.env_yaml, segment=True)
    prepared = prepare_scene(real_scene(ns.env_yaml, ns.point_cloud), cfg)
    write_landmark_list(Path(ns.out), list(prepared.landmarks.values()), cfg.map.pcd_scale_ratio)
    print(json.dumps({"landmarks": len(prepared.landmarks), "out": ns.out}))


def cmd_grounding(args: list[str]) -> None:
    from openfly_agent.toolchain.config import GroundingDataConfig
    from openfly_agent.toolchain.grounding import generate_grounding
    from openfly_agent.utils.config import parse_config

    info = generate_grounding(parse_config(GroundingDataConfig, _config_args(args)))
    print(json.dumps(info["splits"]))


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in COMMANDS:
        raise SystemExit(f"usage: python -m openfly_agent.toolchain {{{','.join(COMMANDS)}}} ...\n{__doc__}")
    setup_logging()
    commands = {
        "generate": cmd_generate,
        "summarize": cmd_summarize,
        "dagger": cmd_dagger,
        "segment": cmd_segment,
        "grounding": cmd_grounding,
    }
    commands[argv[0]](argv[1:])


if __name__ == "__main__":
    main()
