"""Closed-loop evaluation throughput: episodes per minute and the simulator / model time split.

Runs the same episodes through the lockstep runner at batch 1 and at a larger lockstep batch, with the
tiny agent (a checkpoint, or a freshly initialised tiny preset) on CPU, and on CUDA when present.
Prints one JSON line per configuration:

    {"device": "cpu", "batch": 16, "episodes": 32, "steps": 640, "episodes_per_min": ..., "steps_per_s": ...,
     "sim_ms_per_step": ..., "model_ms_per_step": ..., "sim_share": ..., "frame": "128x128", ...}

`sim_ms_per_step` / `model_ms_per_step` are wall-clock times divided by the number of episode steps, so a
batched call is shared among the episodes it serves.

    python bench/eval_throughput.py --dataset_root outputs/datasets/embedded-small --episodes 32
    python bench/eval_throughput.py                         # generates a small dataset in a temp folder
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from openfly_agent.eval.config import EvalConfig  # noqa: E402
from openfly_agent.eval.distributed import ProcessInfo  # noqa: E402
from openfly_agent.eval.factory import embedded_sim_config, load_splits, make_env  # noqa: E402
from openfly_agent.model.config import tiny_config  # noqa: E402
from openfly_agent.model.language.tokenizer import train_bpe_tokenizer  # noqa: E402
from openfly_agent.rollout.agent import AgentPolicy  # noqa: E402
from openfly_agent.rollout.checkpoints import load_agent  # noqa: E402
from openfly_agent.rollout.runner import LockstepRunner  # noqa: E402
from openfly_agent.toolchain.config import GenerateConfig, RenderConfig, SceneConfig  # noqa: E402
from openfly_agent.toolchain.generate import generate  # noqa: E402


def _dataset(args) -> str:
    if args.dataset_root and (Path(args.dataset_root) / "Annotation").is_dir():
        return args.dataset_root
    root = tempfile.mkdtemp(prefix="eval-bench-")
    scenes = SceneConfig(
        train_seeds=[0], unseen_seeds=[1000], trajectories_per_scene=args.episodes, test_seen_fraction=0.9
    )
    generate(
        GenerateConfig(output_dir=root, workers=1, scenes=scenes, render=RenderConfig(128, 128), plots=False)
    )
    return root


def _agent(args, texts, device: str):
    import torch

    from openfly_agent.model.agent import OpenFlyAgent  # lazy: torch + transformers; --help stays fast

    if args.checkpoint:
        return load_agent(args.checkpoint, device, dtype="float32")
    torch.manual_seed(0)
    tokenizer = train_bpe_tokenizer(texts, vocab_size=1024, out_dir=None)
    return OpenFlyAgent.from_model_config(tiny_config(), tokenizer=tokenizer).to(device).eval()


def _measure(agent, episodes, cfg, batch: int, device: str) -> dict:
    import torch

    cfg.batch_size = batch
    env = make_env(cfg, ProcessInfo(), episodes, render=True)
    runner = LockstepRunner(AgentPolicy(agent.new_session()), env, cfg.max_steps, show_progress=False)
    runner.run(episodes[:batch], "warmup")  # GL context, city upload, first kernels
    start = time.perf_counter()
    stats = runner.run(episodes, "bench")
    wall = time.perf_counter() - start
    env.close()
    sim_cfg = embedded_sim_config(cfg, episodes)
    return {
        "device": device,
        "batch": batch,
        "episodes": stats.episodes,
        "steps": stats.steps,
        "policy_calls": stats.policy_calls,
        "max_steps": cfg.max_steps,
        "frame": f"{sim_cfg.width}x{sim_cfg.height}",
        "wall_s": round(wall, 3),
        "episodes_per_min": round(60.0 * stats.episodes / wall, 2),
        "steps_per_s": round(stats.steps / wall, 2),
        "sim_ms_per_step": round(1000.0 * stats.sim_s / stats.steps, 3),
        "model_ms_per_step": round(1000.0 * stats.policy_s / stats.steps, 3),
        "sim_share": round(stats.sim_s / max(stats.sim_s + stats.policy_s, 1e-9), 3),
        "torch_threads": torch.get_num_threads(),
        "load_avg_1m": round(os.getloadavg()[0], 2),
        "machine": platform.processor() or platform.machine(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--dataset_root", default="outputs/datasets/embedded-small")
    parser.add_argument("--checkpoint", default=None, help="agent checkpoint; default: a fresh tiny preset")
    parser.add_argument("--episodes", type=int, default=16, help="episodes per configuration (test splits)")
    parser.add_argument("--max_steps", type=int, default=20)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)

    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    root = _dataset(args)
    cfg = EvalConfig(policy="stop", dataset_root=root, max_episodes=args.episodes, max_steps=args.max_steps)
    episodes = [e for split in load_splits(cfg).values() for e in split][: args.episodes]
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for device in devices:
        agent = _agent(args, [e.instruction for e in episodes], device)
        for batch in args.batches:
            print(json.dumps(_measure(agent, episodes, cfg, batch, device)), flush=True)


if __name__ == "__main__":
    main()
