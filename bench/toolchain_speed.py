"""Toolchain speed: planning and rendering (trajectories/s), complete generation, data loader (samples/s).

    python bench/toolchain_speed.py [--units 60] [--workers 2] [--size 128]

Prints one JSON line per stage:
  planning   route sampling + A* + action conversion + filters, one process, on a 1 km embedded city
  rendering  every kept frame of those trajectories through the embedded simulator, one process
  complete   `generate` end to end (scene preparation, planning, rendering, instructions, parquet writing)
             with `--workers` processes; `trajectories_per_s` = trajectories written / wall time
  loader     NavigationStepDataset over the generated train split through a DataLoader (`samples_per_s`)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from openfly_agent.data.frames import FrameStore
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.toolchain.config import GenerateConfig, SceneConfig
from openfly_agent.toolchain.generate import generate
from openfly_agent.toolchain.pipeline import Rejected, plan_trajectory, prepare_scene
from openfly_agent.toolchain.render import render_poses
from openfly_agent.toolchain.scenes import embedded_scene
from openfly_agent.toolchain.worker import default_simulator
from openfly_agent.utils.config import load_yaml_config

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "toolchain" / "embedded-small.yaml"


def _machine() -> dict:
    return {
        "cpu_count": os.cpu_count(),
        "load_avg_1m": round(os.getloadavg()[0], 2),  # other work on the machine slows the wall-clock figures
        "machine": platform.machine(),
        "python": platform.python_version(),
    }


def _cpu_s() -> float:
    """CPU seconds (user + sys) of this process and its finished children, all threads."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _emit(record: dict) -> None:
    print(json.dumps({"bench": "toolchain_speed", **record, **_machine()}), flush=True)


def bench_planning(cfg: GenerateConfig, units: int):
    start = time.perf_counter()
    prepared = prepare_scene(embedded_scene(0, cfg.scenes), cfg)
    prepare_s = time.perf_counter() - start
    planned, rejected, start, cpu = [], 0, time.perf_counter(), _cpu_s()
    for i in range(units):
        try:
            planned.append(plan_trajectory(prepared, np.random.default_rng(i), cfg))
        except Rejected:
            rejected += 1
    wall, cpu = time.perf_counter() - start, _cpu_s() - cpu
    _emit(
        {
            "stage": "planning",
            "trajectories_per_s": len(planned) / wall,
            "cpu_ms_per_trajectory": 1000 * cpu / max(1, len(planned)),
            "attempts_per_s": units / wall,
            "rejected": rejected,
            "scene_prepare_s": prepare_s,
            "mean_frames": float(np.mean([len(p.seq) for p in planned])),
            "scene": prepared.scene.scene_id,
        }
    )
    return prepared, planned


def bench_rendering(cfg: GenerateConfig, prepared, planned) -> None:
    sim = default_simulator(cfg)
    render_poses(sim, prepared.scene.scene_id, planned[0].seq.poses[:2], 0.0)  # context + scene upload
    start, cpu, frames = time.perf_counter(), _cpu_s(), 0
    for p in planned:
        frames += len(render_poses(sim, prepared.scene.scene_id, p.seq.poses, p.pitch_deg).frames)
    wall, cpu = time.perf_counter() - start, _cpu_s() - cpu
    sim.close()
    _emit(
        {
            "stage": "rendering",
            "trajectories_per_s": len(planned) / wall,
            "frames_per_s": frames / wall,
            "cpu_ms_per_trajectory": 1000 * cpu / len(planned),
            "resolution": [cfg.render.width, cfg.render.height],
        }
    )


def bench_complete(cfg: GenerateConfig, root: Path) -> None:
    start, cpu = time.perf_counter(), _cpu_s()
    summary = generate(cfg, progress=False)
    wall, cpu = time.perf_counter() - start, _cpu_s() - cpu
    n = max(1, summary["trajectories"])
    _emit(
        {
            "stage": "complete",
            "trajectories_per_s": summary["trajectories"] / wall,
            # all processes' CPU time (workers, parent, llvmpipe threads) per written trajectory, scene
            # preparation included; 2 / this = what 2 otherwise idle cores would sustain
            "cpu_s_per_trajectory": cpu / n,
            "trajectories_per_s_2_idle_cores": 2.0 / (cpu / n),
            "trajectories": summary["trajectories"],
            "attempts": summary["attempts"],
            "wall_s": wall,
            "workers": cfg.workers,
            "scenes": len(cfg.scenes.train_seeds) + len(cfg.scenes.unseen_seeds),
            "resolution": [cfg.render.width, cfg.render.height],
        }
    )


def bench_loader(root: Path, workers: int, batches: int = 30) -> None:
    import torch

    from openfly_agent.data.dataset import NavigationStepDataset  # lazy: torch, like `import torch` above

    episodes = load_openfly_dataset(root, "train")
    dataset = NavigationStepDataset(episodes, FrameStore(root), "uniform", capacity=2, set_size=1)
    loader = torch.utils.data.DataLoader(
        dataset,
        batch_size=16,
        shuffle=True,
        num_workers=workers,
        collate_fn=list,
        persistent_workers=workers > 0,
    )
    it, samples = iter(loader), 0
    next(it)  # worker start-up
    start = time.perf_counter()
    for _ in range(batches):
        try:
            samples += len(next(it))
        except StopIteration:
            break
    wall = time.perf_counter() - start
    _emit({"stage": "loader", "samples_per_s": samples / wall, "samples": samples, "num_workers": workers})


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--units", type=int, default=60, help="route attempts for planning / rendering")
    parser.add_argument("--complete_units", type=int, default=60, help="route attempts per scene (complete)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--size", type=int, default=128, help="frame width = height")
    ns = parser.parse_args()
    cfg = load_yaml_config(
        GenerateConfig, CONFIG, [f"--render.width={ns.size}", f"--render.height={ns.size}"]
    )
    prepared, planned = bench_planning(cfg, ns.units)
    bench_rendering(cfg, prepared, planned)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "dataset"
        scenes = SceneConfig(train_seeds=[0, 1], unseen_seeds=[2], trajectories_per_scene=ns.complete_units)
        complete = load_yaml_config(
            GenerateConfig,
            CONFIG,
            [f"--output_dir={root}", f"--workers={ns.workers}", "--dagger.episodes_per_scene=0"],
        )
        complete = dataclasses.replace(complete, scenes=scenes, render=cfg.render)
        bench_complete(complete, root)
        bench_loader(root, ns.workers)


if __name__ == "__main__":
    main()
