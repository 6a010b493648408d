"""Embedded simulator speed: frames per second with RGB + instance buffer read back and boxes computed.

    python bench/sim_fps.py                       # 224 x 224, 1 km^2 city `embedded-0`
    python bench/sim_fps.py --resolutions 224x224 512x512 --modes render step --frames 500

Prints one JSON line per (mode, resolution) with `resolution`, `fps` (median over --repeats runs) and
`scene`. Every frame reads back RGB and the instance buffer and computes the landmark boxes.
`render`: `EmbeddedSimulator.render`, one frame per call, from random poses (10-150 m, a third pitched
-45 deg); `render_batch`: the same poses through `render_many` (16 tiles per framebuffer flush);
`step`: episodes of random actions through `EmbeddedSimulator.step` (dynamics + collision + render);
`vector`: 16 such episodes in lockstep through `VectorSimulator.embedded` (frames rendered together).
`cpu_ms_per_frame` is the CPU time of all threads of the process (llvmpipe rasterises on worker threads)
and `frames_per_cpu_s` its inverse: the rate one dedicated core sustains, a load-independent figure on a
shared machine, where `fps` depends on what else runs (`load_avg_1m`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time

import numpy as np

from openfly_agent import constants as C
from openfly_agent.sim.base import EpisodeSpec
from openfly_agent.sim.city import CityConfig, scene_id_of
from openfly_agent.sim.embedded import EmbeddedSimConfig, EmbeddedSimulator
from openfly_agent.sim.vector import VectorSimulator
from openfly_agent.utils.geometry import Pose

STEP_ACTIONS = [
    C.ACTION_FORWARD, C.ACTION_FORWARD_6, C.ACTION_FORWARD_9, C.ACTION_TURN_LEFT, C.ACTION_TURN_RIGHT,
    C.ACTION_ASCEND, C.ACTION_DESCEND,
]  # fmt: skip


def _random_poses(rng: np.random.Generator, half: float, n: int) -> list[tuple[Pose, float]]:
    poses = []
    for _ in range(n):
        pose = Pose(
            rng.uniform(-half, half),
            rng.uniform(-half, half),
            rng.uniform(10, 150),
            rng.uniform(-math.pi, math.pi),
        )
        poses.append((pose, -45.0 if rng.random() < 1 / 3 else 0.0))
    return poses


def bench_render(sim: EmbeddedSimulator, scene_id: str, poses, batch: int) -> tuple[float, float]:
    """(frames per second, mean number of boxes per frame), `batch` views per call."""
    sim.render_many(scene_id, [p for p, _ in poses[:batch]], [a for _, a in poses[:batch]])  # warm-up
    boxes = 0
    start = time.perf_counter()
    for first in range(0, len(poses), batch):
        chunk = poses[first : first + batch]
        if batch == 1:
            frames = [sim.render(scene_id, *chunk[0])]
        else:
            frames = sim.render_many(scene_id, [p for p, _ in chunk], [a for _, a in chunk])
        boxes += sum(len(f.boxes) for f in frames)
    return len(poses) / (time.perf_counter() - start), boxes / len(poses)


def _random_episode(rng: np.random.Generator, scene_id: str, half: float, k: int) -> EpisodeSpec:
    pose = Pose(rng.uniform(-half, half), rng.uniform(-half, half), rng.uniform(20, 120), rng.uniform(-3, 3))
    return EpisodeSpec(f"bench-{k}", scene_id, pose)


def bench_step(sim: EmbeddedSimulator, scene_id: str, rng: np.random.Generator, n_steps: int, envs: int):
    """(steps/s, collisions per step): random actions, episodes of <= 40 steps, `envs` in lockstep."""
    half = sim.city(scene_id).bounds.xmax * 0.9
    vec = VectorSimulator(sims=[sim] + [sim.sibling() for _ in range(envs - 1)])
    steps = collisions = 0
    start = time.perf_counter()
    vec.reset([_random_episode(rng, scene_id, half, k) for k in range(envs)])
    lengths = [0] * envs  # actions of each slot's episode
    while steps < n_steps:
        for i, active in enumerate(vec.active):
            if not active or lengths[i] >= 40:
                vec.reset_env(i, _random_episode(rng, scene_id, half, steps + i))
                lengths[i] = 0
        _, infos = vec.step([int(rng.choice(STEP_ACTIONS)) for _ in range(envs)])
        lengths = [n + 1 for n in lengths]
        steps += envs
        collisions += sum(info.collided for info in infos)
    elapsed = time.perf_counter() - start
    for extra in vec.sims[1:]:
        extra.close()
    return steps / elapsed, collisions / steps


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seed", type=int, default=0, help="city seed (scene embedded-<seed>)")
    parser.add_argument("--size-m", type=float, default=1000.0, help="city side in metres")
    parser.add_argument("--resolutions", nargs="+", default=["224x224"], help="WxH")
    modes = ["render", "render_batch", "step", "vector"]
    parser.add_argument("--modes", nargs="+", default=modes, choices=modes)
    parser.add_argument("--frames", type=int, default=400, help="frames (or steps) per run")
    parser.add_argument("--repeats", type=int, default=3, help="runs per setting; the median is reported")
    args = parser.parse_args()
    scene_id = scene_id_of(args.seed)
    for resolution in args.resolutions:
        width, height = (int(v) for v in resolution.lower().split("x"))
        cfg = EmbeddedSimConfig(width=width, height=height, city=CityConfig(size_m=args.size_m))
        with EmbeddedSimulator(cfg) as sim:
            city = sim.city(scene_id)
            for mode in args.modes:
                runs, cpu_ms, extra = [], [], 0.0
                for repeat in range(args.repeats):
                    cpu_start = time.process_time()
                    rng = np.random.default_rng(repeat)
                    if mode in ("render", "render_batch"):
                        poses = _random_poses(rng, args.size_m / 2, args.frames)
                        fps, extra = bench_render(
                            sim, scene_id, poses, 1 if mode == "render" else cfg.max_batch
                        )
                    else:
                        fps, extra = bench_step(sim, scene_id, rng, args.frames, 1 if mode == "step" else 16)
                    runs.append(fps)
                    cpu_ms.append(1000.0 * (time.process_time() - cpu_start) / args.frames)
                record = {
                    "bench": "sim_fps",
                    "mode": mode,
                    "resolution": f"{width}x{height}",
                    "fps": round(statistics.median(runs), 1),
                    "fps_runs": [round(r, 1) for r in runs],
                    "cpu_ms_per_frame": round(statistics.median(cpu_ms), 2),  # all threads of this process
                    "frames_per_cpu_s": round(1000.0 / statistics.median(cpu_ms), 1),
                    "scene": scene_id,
                    "scene_size_m": args.size_m,
                    "buildings": len(city.buildings),
                    "box_parts": len(city.box_table()["lo"]),
                    "frames_per_run": args.frames,
                    "readback": "rgb+instance_ids",
                    ("mean_boxes_per_frame" if mode.startswith("render") else "collisions_per_step"): round(
                        extra, 3
                    ),
                    "gl_renderer": sim.renderer.gl_renderer,
                    "cpu_count": os.cpu_count(),
                    "load_avg_1m": round(os.getloadavg()[0], 2),
                }
                print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
