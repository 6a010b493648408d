"""Builders behind `run(cfg)`: the evaluated episodes, the lockstep environment and the policies."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.frames import FrameStore
from openfly_agent.data.generation_settings import read_generation_settings
from openfly_agent.data.openfly_reader import load_openfly_dataset, non_strict_hint
from openfly_agent.data.schema import Episode, SchemaError
from openfly_agent.eval.baselines import make_baseline
from openfly_agent.eval.config import (
    AGENT_POLICIES,
    AGENT_TRUE_BOX,
    SIM_EMBEDDED,
    BridgeSimSettings,
    EngineUnreachableError,
    EvalConfig,
    EvalInputError,
    SimSettings,
)
from openfly_agent.eval.distributed import ProcessInfo
from openfly_agent.rollout.agent import AgentPolicy
from openfly_agent.rollout.checkpoints import load_agent, resolve_device
from openfly_agent.sim.blind import BlindEmbeddedSimulator, CityCache
from openfly_agent.sim.bridges.base import BridgeError
from openfly_agent.sim.embedded import EmbeddedSimConfig
from openfly_agent.sim.embedded_scenes import EMBEDDED_SCENE_FORM, city_config, is_embedded_scene
from openfly_agent.sim.occupancy import OccupancyGrid
from openfly_agent.sim.pointcloud import read_points
from openfly_agent.sim.real_scene import ENGINE_AIRSIM, ENGINE_GS, ENGINE_UE, engine_of
from openfly_agent.sim.scene import SceneBounds
from openfly_agent.sim.vector import VectorSimulator

logger = logging.getLogger(__name__)

DEFAULT_FRAME_SIZE = 224
BRIDGE_OF_ENGINE = {
    ENGINE_UE: "unrealcv",
    ENGINE_AIRSIM: "airsim",
    ENGINE_GS: "gs_http",
}  # --sim.type per engine


def subsample(episodes: list[Episode], count: int | None) -> list[Episode]:
    """`count` episodes evenly spaced over `episodes` (all when None), so every scene and category is kept."""
    if count is None or count >= len(episodes):
        return list(episodes)
    picks = np.unique(np.linspace(0, len(episodes) - 1, count).round().astype(int))
    return [episodes[i] for i in picks]


def load_splits(cfg: EvalConfig) -> dict[str, list[Episode]]:
    """{split: episodes sorted by id} for every split of `cfg` (`max_episodes` evenly spaced ones when set)."""
    return subsample_splits(load_full_splits(cfg), cfg.max_episodes)


def subsample_splits(full: dict[str, list[Episode]], count: int | None) -> dict[str, list[Episode]]:
    """`subsample` of every split (all of each when `count` is None)."""
    out = {split: subsample(episodes, count) for split, episodes in full.items()}
    for split, episodes in out.items():
        if len(episodes) < len(full[split]):
            logger.info(
                "%s: evaluating %d of %d episodes (max_episodes)", split, len(episodes), len(full[split])
            )
    return out


def load_full_splits(cfg: EvalConfig) -> dict[str, list[Episode]]:
    """{split: every episode, sorted by id} for every split of `cfg` (before `max_episodes`).

    Raises:
        FileNotFoundError: the dataset root or a split's annotation is missing, with the path and a hint.
    """
    routes = (  # the two ways to a dataset, as train.py names them
        f"generate it (python -m openfly_agent.toolchain generate --output_dir={cfg.dataset_root}), or download "
        f"the released OpenFly data as {C.RELEASED_DATA_CARD} says and pass its folder as --dataset_root"
    )
    if not Path(cfg.dataset_root).is_dir():
        raise FileNotFoundError(f"dataset root {cfg.dataset_root} does not exist: {routes}")
    out = {}
    for split in cfg.split:
        try:
            episodes = load_openfly_dataset(cfg.dataset_root, split, cfg.reader)
        except FileNotFoundError as err:
            raise FileNotFoundError(f"{err}: {routes}") from err
        except SchemaError as err:
            hint = non_strict_hint(err, "--reader.strict") if cfg.reader.strict else ""
            if not hint:
                raise
            raise SchemaError(err.file, err.record, err.field_name, err.problem + hint) from err
        episodes = sorted(episodes, key=lambda e: e.episode_id)
        if not episodes:
            raise EvalInputError(f"{cfg.dataset_root}: split {split!r} has no episodes")
        out[split] = episodes
        logger.info("%s: %d episodes from %s", split, len(episodes), cfg.dataset_root)
    return out


def check_simulator_scenes(cfg: EvalConfig, episodes: list[Episode]) -> None:
    """The embedded simulator flies only the embedded cities: refuse any other scene before a model loads or an
    output is written, naming the bridge that flies it.

    Raises:
        EvalInputError: one line naming the first scene that is not embedded, how many episodes are in such
            scenes, and the `--sim.type` choices that fly them.
    """
    if cfg.sim.type != SIM_EMBEDDED:
        return
    foreign = [e for e in episodes if not is_embedded_scene(e.scene_id)]
    if not foreign:
        return
    scene = foreign[0].scene_id
    try:
        hint = f" (this one: --sim.type={BRIDGE_OF_ENGINE[engine_of(scene)]})"
    except ValueError:
        hint = ""
    bridges = "|".join(name for name in SimSettings.get_known_choices() if name != SIM_EMBEDDED)
    raise EvalInputError(
        f"--sim.type={SIM_EMBEDDED} flies only the embedded cities (scene ids {EMBEDDED_SCENE_FORM}); episode "
        f"scene {scene!r} ({len(foreign)} of {len(episodes)} episodes are not embedded) needs a bridge: "
        f"--sim.type={bridges}{hint}, see configs/eval/released-*.yaml and docs/BRIDGES.md"
    )


def dataset_frame_size(root: str, episodes: list[Episode]) -> tuple[int, int] | None:
    """(height, width) of the dataset frames (its first frame), or None when the dataset has no frames."""
    if not episodes:
        return None
    try:
        frame = FrameStore(root).frame(episodes[0], 0)
    except (FileNotFoundError, KeyError, OSError) as err:
        logger.info("no frames under %s (%s); rendering at %d px", root, err, DEFAULT_FRAME_SIZE)
        return None
    return int(frame.shape[0]), int(frame.shape[1])


def scene_occupancy(template: str, scene_id: str, voxel_m: float):
    """Occupancy grid of a real scene from its point cloud (`template` with `{scene_id}`), for collisions."""
    path = Path(template.format(scene_id=scene_id))
    if not path.is_file():
        raise FileNotFoundError(f"sim.occupancy_pcd: no point cloud for scene {scene_id} at {path}")
    points = read_points(path)  # (N, 3) metres
    lo, hi = points.min(axis=0) - voxel_m, points.max(axis=0) + voxel_m
    bounds = SceneBounds(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])
    return OccupancyGrid.from_points(points, bounds, voxel_m)


class _BridgeEnv(VectorSimulator):
    """One bridge; its collision occupancy follows the scene of the episode being reset."""

    def __init__(self, bridge, settings: BridgeSimSettings):
        super().__init__(sims=[bridge])
        self.settings = settings
        self._occupancy: dict[str, object] = {}

    def reset_env(self, slot: int, spec):
        if self.settings.occupancy_pcd:
            if spec.scene_id not in self._occupancy:
                self._occupancy[spec.scene_id] = scene_occupancy(
                    self.settings.occupancy_pcd, spec.scene_id, self.settings.occupancy_voxel_m
                )
            self.sims[slot].occupancy = self._occupancy[spec.scene_id]
        return super().reset_env(slot, spec)


def make_bridge_env(settings: BridgeSimSettings, info: ProcessInfo) -> VectorSimulator:
    """One engine bridge per process (`port + rank` when `port_per_rank`), as a lockstep environment of width 1.

    Raises:
        EngineUnreachableError: the engine does not answer (connection and handshake are tried at once, so
            a wrong host or port, or an engine that is not running, ends the run before any episode).
    """
    bridge_cls = settings.bridge_class
    config = settings.bridge_config()
    if settings.port_per_rank and info.world_size > 1:
        port = (config.port or bridge_cls.default_port) + info.rank
        config = dataclasses.replace(config, port=port)
    logger.info("%s bridge at %s:%s", settings.type, config.host, config.port or bridge_cls.default_port)
    bridge = bridge_cls(config)
    try:
        bridge.connect()
    except BridgeError as err:
        raise EngineUnreachableError(str(err)) from err
    return _BridgeEnv(bridge, settings)


def embedded_sim_config(cfg: EvalConfig, episodes: list[Episode]):
    """`EmbeddedSimConfig` that rebuilds the dataset's cities at its frame size, counting collisions.

    Frame size: `sim.width/height`, else the generation settings of the dataset, else its first frame, else
    224. The city parameters come from the generation settings (the generator's defaults without them).
    """
    generated = read_generation_settings(cfg.dataset_root)
    size = None
    if generated is not None:
        size = (generated.height, generated.width)
    elif cfg.sim.width is None or cfg.sim.height is None:
        size = dataset_frame_size(cfg.dataset_root, episodes)
    height = cfg.sim.height or (size[0] if size else DEFAULT_FRAME_SIZE)
    width = cfg.sim.width or (size[1] if size else DEFAULT_FRAME_SIZE)
    city = {"city": city_config(generated.city_size_m, generated.city_buildings)} if generated else {}
    return EmbeddedSimConfig(
        width=int(width), height=int(height), collision="count", **city,
        max_cached_scenes=max(4, cfg.batch_size),  # lockstep slots may fly in as many cities at once
    )  # fmt: skip


def make_env(
    cfg: EvalConfig, info: ProcessInfo, episodes: list[Episode], render: bool = True
) -> VectorSimulator:
    """The lockstep environment of `cfg.sim`: `batch_size` embedded environments (rendering or blind), or a bridge."""
    if isinstance(cfg.sim, BridgeSimSettings):
        if cfg.batch_size > 1:
            logger.info("%s: one engine per process, so episodes run one at a time", cfg.sim.type)
        return make_bridge_env(cfg.sim, info)
    sim_cfg = embedded_sim_config(cfg, episodes)
    if not render:
        cities = CityCache(sim_cfg)
        return VectorSimulator(sims=[BlindEmbeddedSimulator(sim_cfg, cities) for _ in range(cfg.batch_size)])
    logger.info(
        "embedded simulator: %d x %d px, %d environments", sim_cfg.width, sim_cfg.height, cfg.batch_size
    )
    return VectorSimulator.embedded(sim_cfg, num_envs=cfg.batch_size)


def make_policy(name: str, cfg: EvalConfig, episodes: list[Episode], info: ProcessInfo):
    """The policy called `name`: the agent of `cfg.checkpoint` (`agent_true_box`: fed the true target box), or a
    baseline."""
    if name not in AGENT_POLICIES:
        return make_baseline(
            name, episodes, seed=cfg.seed, oracle_mode=cfg.oracle_mode, box_servo=cfg.box_servo
        )

    device = resolve_device(cfg.device, getattr(info.state, "device", None))
    settings = cfg.agent
    agent = load_agent(
        cfg.checkpoint,
        device,
        settings.dtype,
        settings.decode_rule,
        settings.unnorm_key,
        settings.model_config,
    )
    session = agent.new_session(settings.memory_probe)
    return AgentPolicy(session, name, true_boxes=name == AGENT_TRUE_BOX)
