"""Generate the grounding dataset: frames of a navigation dataset's cities, one expression per visible landmark.

Poses come from the trajectories of the chosen splits of a navigation dataset (the train split by default:
the alignment data never sees a test city). Every kept pose is rendered as recorded, and `yaw_copies` more
times with its yaw turned by a random angle (views a trajectory never looks at). Every landmark whose box
covers at least `min_box_area` gets a referring expression that matches no other visible landmark
(toolchain/expressions.py). Scenes are written one at a time (resumable): data/grounding.py has the layout.

    python -m openfly_agent.toolchain grounding --source_root outputs/datasets/embedded-small \
        --output_dir outputs/datasets/grounding-small
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.frames import encode_image
from openfly_agent.data.grounding import finalize_grounding, scene_done, write_scene
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.data.schema import Episode
from openfly_agent.sim.city import CityConfig
from openfly_agent.sim.embedded import EmbeddedSimConfig, EmbeddedSimulator
from openfly_agent.toolchain.config import GroundingDataConfig
from openfly_agent.toolchain.expressions import frame_expressions
from openfly_agent.utils.config import save_config
from openfly_agent.utils.geometry import Pose
from openfly_agent.utils.progress import progress_bar

logger = logging.getLogger(__name__)

CONFIG_JSON = "meta/grounding_config.json"


def source_render_settings(source_root: str | Path) -> tuple[int, int, CityConfig]:
    """(width, height, city config) the source dataset was generated with (its saved toolchain config)."""
    path = Path(source_root) / C.TOOLCHAIN_CONFIG_JSON
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found: the grounding data renders the cities of a dataset made by the toolchain "
            "(python -m openfly_agent.toolchain generate)"
        )
    data = json.loads(path.read_text())
    render, scenes = data.get("render", {}), data.get("scenes", {})
    city = CityConfig(size_m=float(scenes.get("city_size_m", CityConfig.size_m)))
    if scenes.get("city_buildings") is not None:
        city = CityConfig(size_m=city.size_m, n_buildings=int(scenes["city_buildings"]))
    return int(render.get("width", 128)), int(render.get("height", 128)), city


def frame_poses(episode: Episode, cfg: GroundingDataConfig, rng: np.random.Generator) -> list[Pose]:
    """The episode's kept poses, each followed by `yaw_copies` copies with a random yaw offset."""
    jitter = math.radians(cfg.yaw_jitter_deg)
    poses = []
    for (x, y, z), yaw in zip(episode.positions, episode.yaws):
        poses.append(Pose(float(x), float(y), float(z), float(yaw)))
        for _ in range(cfg.yaw_copies):
            poses.append(Pose(float(x), float(y), float(z), float(yaw + rng.uniform(-jitter, jitter))))
    return poses


def scene_rows(
    sim: EmbeddedSimulator, episodes: list[Episode], cfg: GroundingDataConfig, seed: int
) -> list[dict]:
    """Rendered frames of one scene's episodes as grounding rows (frames without a described landmark dropped)."""
    rows = []
    for episode in episodes:
        rng = np.random.default_rng([seed, hash_text(episode.episode_id)])
        city = sim.city(episode.scene_id)
        poses = frame_poses(episode, cfg, rng)
        for k, (pose, obs) in enumerate(
            zip(poses, sim.render_many(episode.scene_id, poses, episode.pitch_deg))
        ):
            visible = {
                lid: (city.landmark(lid), np.asarray(box, dtype=np.float64))
                for lid, box in (obs.boxes or {}).items()
                if float(box[2] * box[3]) >= cfg.min_box_area
            }
            if not visible:
                continue
            expressions = frame_expressions(visible, rng)
            frame_id = f"{episode.episode_id.rsplit('/', 1)[-1]}_{k}"
            rows.append(
                {
                    "image": {"bytes": encode_image(obs.rgb), "path": f"{frame_id}.png"},
                    "frame_id": frame_id,
                    "scene_id": episode.scene_id,
                    "split": episode.split,
                    "source_episode": episode.episode_id,
                    "pose": [float(v) for v in pose.as_array()],
                    "pitch_deg": float(episode.pitch_deg),
                    "landmark_ids": [e.landmark_id for e in expressions],
                    "expressions": [e.text for e in expressions],
                    "boxes": [list(e.box) for e in expressions],
                    "relations": [e.relation or "" for e in expressions],
                }
            )
    return rows


def hash_text(text: str) -> int:
    """A stable 63-bit hash of a string (Python's `hash` is salted per process)."""
    return int.from_bytes(hashlib.sha256(text.encode("utf-8")).digest()[:8], "little") >> 1


def generate_grounding(cfg: GroundingDataConfig, progress: bool = True) -> dict:
    """Generate (or resume) the grounding dataset of `cfg`; returns meta/info.json's content."""
    root = Path(cfg.output_dir)
    root.mkdir(parents=True, exist_ok=True)
    (root / CONFIG_JSON).parent.mkdir(parents=True, exist_ok=True)
    save_config(cfg, root / CONFIG_JSON)
    width, height, city = source_render_settings(cfg.source_root)
    by_scene: dict[str, list[Episode]] = defaultdict(list)
    for split in cfg.splits:
        for episode in load_openfly_dataset(cfg.source_root, split, ReaderOptions(takeoff_landing="trim")):
            by_scene[episode.scene_id].append(episode)
    todo = [scene for scene in sorted(by_scene) if not scene_done(root, scene)]
    logger.info("grounding data %s: %d of %d scenes to render", root, len(todo), len(by_scene))
    if todo:
        sim = EmbeddedSimulator(EmbeddedSimConfig(width=width, height=height, city=city, max_cached_scenes=1))
        try:
            for scene in progress_bar(todo, desc="grounding scenes", disable=not progress):
                episodes = sorted(by_scene[scene], key=lambda e: e.episode_id)
                write_scene(root, scene, scene_rows(sim, episodes, cfg, cfg.seed), cfg.frames_per_part)
        finally:
            sim.close()
    extra = {
        "source_root": str(cfg.source_root),
        "min_box_area": cfg.min_box_area,
        "frame_size": [height, width],
    }
    return finalize_grounding(root, extra)
