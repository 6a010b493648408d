"""RL stage speed: rollouts per second and seconds per update of `train.py --stage=rl` on the tiny preset.

Runs the RL stage's own update (training/rl_trainer.py `set_up_rl`, `one_update`) on the embedded city of a
small generated dataset and splits each update into its two phases, as the stage logs them:
`rollout_s` (the groups flown: the agent's batched sampling and the simulator's rendering) and `update_s` (the
replay of every kept step through the training forward, three passes each, and the optimizer steps).
Prints one JSON line per timed update and a summary line:

    {"update": 2, "rollouts": 4, "rollout_steps": 31, "rollout_s": ..., "update_s": ..., "rollout_steps_per_s": ...,
     "rollouts_per_s": ..., "samples_trained": ...}
    {"summary": true, "updates": 2, "rollout_steps_per_s": ..., "rollouts_per_s": ..., "s_per_update": ...,
     "markdown": "| tiny, 64x64, 2 x 2 rollouts of <= 20 steps | ... |", ...}

The `markdown` value is the row of docs/BENCHMARKS.md's RL table. Without `--checkpoint` the agent is a
navigation run of `--nav_steps` steps trained here first (a near-random policy: its flights run long, the
slow case), and the reward has the progress term (`--progress_weight`), so the groups' rewards differ and every
update trains (with success alone, a group of failures is left out and its update trains nothing); the first
`--warmup` updates (GL context, city upload, first kernels) are run but not timed.

    python bench/rl_rollouts.py                                       # generates a small dataset in a temp folder
    python bench/rl_rollouts.py --dataset_root outputs/datasets/embedded-small --checkpoint outputs/recipe/navigation
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from openfly_agent import constants as C  # noqa: E402
from openfly_agent.data.generation_settings import read_generation_settings  # noqa: E402
from openfly_agent.toolchain.config import (  # noqa: E402
    GenerateConfig,
    RenderConfig,
    RouteConfig,
    SceneConfig,
)
from openfly_agent.toolchain.generate import generate  # noqa: E402
from openfly_agent.training.config import TrainConfig  # noqa: E402
from openfly_agent.utils.config import parse_config  # noqa: E402

TRAIN_CONFIG = REPO / "configs" / "train" / "tiny.yaml"
QUIET = ["--logging.tracker=none", "--checkpoint.save_interval=0", "--cpu=true"]


def _dataset(args, work: Path) -> str:
    """`--dataset_root` when it holds a dataset, else a small one generated into `work`: three 300 m cities (two
    for train / test_seen, one unseen) with short routes, as the training tests' dataset."""
    if args.dataset_root and (Path(args.dataset_root) / "Annotation").is_dir():
        return args.dataset_root
    root = work / "dataset"
    scenes = SceneConfig(
        train_seeds=[0, 2],
        unseen_seeds=[1],
        trajectories_per_scene=args.routes,
        test_seen_fraction=0.3,
        city_size_m=300.0,
        city_buildings=30,
    )
    route = RouteConfig(height_min_m=10.0, height_max_m=40.0, min_dist_m=40.0, max_dist_m=90.0)
    cfg = GenerateConfig(
        output_dir=str(root),
        workers=1,
        scenes=scenes,
        route=route,
        render=RenderConfig(args.frame, args.frame),
        plots=False,
    )
    generate(cfg, progress=False)
    return str(root)


def _checkpoint(args, root: str, work: Path) -> str:
    """`--checkpoint`, else a navigation run of `--nav_steps` steps of the tiny preset trained here."""
    if args.checkpoint:
        return args.checkpoint
    from openfly_agent.training.trainer import train  # lazy: torch + transformers; --help stays fast

    folder = work / "navigation"
    cfg = parse_config(
        TrainConfig,
        ["--config_path", str(TRAIN_CONFIG), f"--data.root={root}", f"--output_dir={folder}",
         f"--steps={args.nav_steps}", "--validation.interval=0", "--validation.final_eval=false", *QUIET],
    )  # fmt: skip
    train(cfg)
    _reset_accelerate()
    return str(folder)


def _reset_accelerate() -> None:
    """accelerate's process-wide state forgotten, so the RL stage sets up one process of its own."""
    from accelerate.state import AcceleratorState, GradientState

    AcceleratorState._reset_state(reset_partial_state=True)
    GradientState._reset_state()


def rl_config(args, root: str, checkpoint: str, output_dir: Path) -> TrainConfig:
    """train.py --stage=rl of the timed run: `warmup + updates` updates of the sizes asked for."""
    return parse_config(
        TrainConfig,
        ["--config_path", str(TRAIN_CONFIG), f"--stage={C.STAGE_RL}", f"--init.checkpoint={checkpoint}",
         f"--data.root={root}", f"--output_dir={output_dir}", f"--steps={args.warmup + args.updates}",
         f"--rl.group_size={args.group_size}", f"--rl.episodes_per_update={args.episodes}",
         f"--rl.max_steps={args.max_steps}", f"--rl.num_envs={args.num_envs}",
         f"--rl.progress_weight={args.progress_weight}", *QUIET],
    )  # fmt: skip


def update_figures(logs: dict, rollouts: int) -> dict:
    """One update's figures from the stage's own logs (`rollout_s`, `update_s`, `rollout_steps`)."""
    return {
        "rollouts": rollouts,
        "rollout_steps": int(logs["rollout_steps"]),
        "rollout_s": round(logs["rollout_s"], 3),
        "update_s": round(logs["update_s"], 3),
        "rollout_steps_per_s": round(logs["rollout_steps"] / logs["rollout_s"], 2),
        "rollouts_per_s": round(rollouts / logs["rollout_s"], 3),
        "samples_trained": int(logs["samples_trained"]),
    }


def summary(timed: list[dict], args, frame: str) -> dict:
    """The timed updates together: rates over their summed phase times, seconds per update on average."""
    steps = sum(u["rollout_steps"] for u in timed)
    rollouts = sum(u["rollouts"] for u in timed)
    rollout_s = sum(u["rollout_s"] for u in timed)
    update_s = sum(u["update_s"] for u in timed)
    figures = {
        "summary": True,
        "updates": len(timed),
        "rollouts": rollouts,
        "rollout_steps": steps,
        "samples_trained": sum(u["samples_trained"] for u in timed),
        "rollout_steps_per_s": round(steps / rollout_s, 2),
        "rollouts_per_s": round(rollouts / rollout_s, 3),
        "rollout_s_per_update": round(rollout_s / len(timed), 2),
        "update_s_per_update": round(update_s / len(timed), 2),
        "s_per_update": round((rollout_s + update_s) / len(timed), 2),
        "frame": frame,
        "load_avg_1m": round(os.getloadavg()[0], 2),
        "machine": platform.processor() or platform.machine(),
    }
    figures["markdown"] = (
        f"| tiny, {frame}, {args.episodes} x {args.group_size} rollouts of <= {args.max_steps} steps, "
        f"{args.num_envs} envs | {len(timed)} | {figures['rollout_steps_per_s']} | {figures['rollouts_per_s']} "
        f"| {figures['rollout_s_per_update']} + {figures['update_s_per_update']} = {figures['s_per_update']} "
        f"| {figures['load_avg_1m']} |"
    )
    return figures


def measure(args, work: Path) -> list[dict]:
    """Run the RL updates in `work`; print and return one record per timed update, then the summary."""
    from openfly_agent.training.accelerator import closing_trackers  # lazy: torch; --help stays fast
    from openfly_agent.training.rl_trainer import embedded_env, one_update, set_up_rl  # lazy: as above

    root = _dataset(args, work)
    checkpoint = _checkpoint(args, root, work)
    run = set_up_rl(rl_config(args, root, checkpoint, work / "rl"))
    env = embedded_env(run.cfg, run.splits, run.profile)
    rollouts = args.episodes * args.group_size
    timed = []
    with env, closing_trackers(run.accelerator):
        for update in range(1, args.warmup + args.updates + 1):
            logs = one_update(run, env)
            if update > args.warmup:
                record = {"update": update, **update_figures(logs, rollouts)}
                print(json.dumps(record), flush=True)
                timed.append(record)
    _reset_accelerate()
    generated = read_generation_settings(root)
    frame = f"{generated.width}x{generated.height}" if generated else "?"
    figures = summary(timed, args, frame)
    print(json.dumps(figures), flush=True)
    return [*timed, figures]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--dataset_root", default=None, help="default: a small dataset generated in a temp folder"
    )
    parser.add_argument(
        "--checkpoint", default=None, help="navigation run; default: --nav_steps trained here"
    )
    parser.add_argument(
        "--nav_steps", type=int, default=2, help="steps of the navigation run made without one"
    )
    parser.add_argument(
        "--routes", type=int, default=10, help="route attempts per city of the generated dataset"
    )
    parser.add_argument("--frame", type=int, default=64, help="frame size of the generated dataset (px)")
    parser.add_argument("--updates", type=int, default=2, help="timed updates")
    parser.add_argument("--warmup", type=int, default=1, help="updates run first, not timed")
    parser.add_argument("--episodes", type=int, default=2, help="rl.episodes_per_update")
    parser.add_argument("--group_size", type=int, default=2, help="rl.group_size")
    parser.add_argument("--max_steps", type=int, default=20, help="rl.max_steps")
    parser.add_argument("--num_envs", type=int, default=4, help="rl.num_envs")
    parser.add_argument(
        "--progress_weight",
        type=float,
        default=1.0,
        help="rl.progress_weight (0: a group of failures trains nothing)",
    )
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    args = parser.parse_args(argv)
    if args.updates < 1 or args.warmup < 0:
        parser.error("--updates must be >= 1 and --warmup >= 0")
    return args


def main(argv: list[str] | None = None) -> list[dict]:
    args = parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory(prefix="rl-bench-") as work:
        return measure(args, Path(work))


if __name__ == "__main__":
    main()
