"""The embedded simulator: procedural cities + the moderngl renderer + dynamics + occupancy collisions.

`EmbeddedSimulator` runs one episode at a time; `sibling()` gives more simulators that share its GL
context and city cache (what `VectorSimulator.embedded` uses to step many episodes in lockstep).
No network, no GPU needed; the GL context is created lazily in the process that renders.
"""

from __future__ import annotations

import logging
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from openfly_agent import constants as C
from openfly_agent.sim.base import EpisodeSpec, Observation, StepInfo
from openfly_agent.sim.city import City, CityConfig, generate_city, parse_scene_id
from openfly_agent.sim.collision import check_policy, motion_collides
from openfly_agent.sim.dynamics import step_motion
from openfly_agent.sim.renderer import CityRenderer
from openfly_agent.utils.geometry import Pose

logger = logging.getLogger(__name__)


@dataclass
class EmbeddedSimConfig:
    """Image, camera, city and collision settings of the embedded simulator."""

    width: int = 224
    height: int = 224
    hfov_deg: float = C.CAMERA_HFOV_DEG
    city: CityConfig = field(default_factory=CityConfig)
    collision: str = "end"  # "end" | "count" | "ignore" (see sim/collision.py)
    voxel_size: float = 2.0  # metres, occupancy used for collisions
    render_depth: bool = False  # fill Observation.depth (metres along the view axis)
    min_box_pixels: int = 16  # a landmark needs this many visible pixels to get a box
    return_instance_ids: bool = False  # put the (H, W) int32 instance image in Observation.extra
    max_batch: int = 16  # views rendered per framebuffer flush (lockstep envs, trajectories)
    max_cached_scenes: int = 4  # cities (and GPU buffers) kept per process; >= scenes run at once
    egl_device: int | None = None  # EGL device index on multi-GPU machines; None = default

    def __post_init__(self) -> None:
        check_policy(self.collision)
        if self.width < 8 or self.height < 8:
            raise ValueError(f"EmbeddedSimConfig.width/height must be >= 8, got {self.width} x {self.height}")
        if self.voxel_size <= 0:
            raise ValueError(f"EmbeddedSimConfig.voxel_size must be > 0, got {self.voxel_size}")
        if self.max_batch < 1:
            raise ValueError(f"EmbeddedSimConfig.max_batch must be >= 1, got {self.max_batch}")
        if self.min_box_pixels < 1:
            raise ValueError(f"EmbeddedSimConfig.min_box_pixels must be >= 1, got {self.min_box_pixels}")


class _Backend:
    """What simulators of one process share: the renderer (GL context) and the city cache."""

    def __init__(self, cfg: EmbeddedSimConfig):
        self.cfg = cfg
        self.renderer = CityRenderer(
            cfg.width,
            cfg.height,
            cfg.hfov_deg,
            min_box_pixels=cfg.min_box_pixels,
            max_batch=cfg.max_batch,
            max_cached_scenes=cfg.max_cached_scenes,
            egl_device=cfg.egl_device,
        )
        self.generated: OrderedDict[str, City] = OrderedDict()
        self.alive: weakref.WeakValueDictionary[str, City] = weakref.WeakValueDictionary()  # still in use
        self.registered: dict[str, City] = {}
        self.users = 0

    def observe(self, requests: Sequence[tuple[City, Pose, float]]) -> list[Observation]:
        """Observations of (city, pose, pitch) requests, rendered in batches per city, in request order."""
        by_city: dict[str, list[int]] = {}
        for i, (city, _, _) in enumerate(requests):
            by_city.setdefault(city.scene_id, []).append(i)
        out: list[Observation | None] = [None] * len(requests)
        for indices in by_city.values():
            city = requests[indices[0]][0]
            poses = [requests[i][1] for i in indices]
            pitches = [requests[i][2] for i in indices]
            frames = self.renderer.render_batch(
                city, poses, pitches, depth=self.cfg.render_depth, ids=self.cfg.return_instance_ids
            )
            for i, pose, pitch, frame in zip(indices, poses, pitches, frames):
                extra = {
                    "pixel_counts": frame.pixel_counts,
                    "scene_id": city.scene_id,
                    "pitch_deg": float(pitch),
                }
                if frame.instance_ids is not None:
                    extra["instance_ids"] = frame.instance_ids
                out[i] = Observation(
                    rgb=frame.rgb, pose=pose, boxes=frame.boxes, depth=frame.depth, extra=extra
                )
        return out

    def city(self, scene_id: str) -> City:
        if scene_id in self.registered:
            return self.registered[scene_id]
        if scene_id not in self.generated:
            # a city evicted from the cache but still held by a running episode is reused, not rebuilt
            city = self.alive.get(scene_id) or generate_city(parse_scene_id(scene_id), self.cfg.city)
            self.generated[scene_id] = self.alive[scene_id] = city
            while len(self.generated) > self.cfg.max_cached_scenes:
                self.generated.popitem(last=False)
        self.generated.move_to_end(scene_id)
        return self.generated[scene_id]


class EmbeddedSimulator:
    """A `Simulator` over embedded cities. Scenes are `embedded-<seed>` or cities added by `register_city`."""

    def __init__(self, cfg: EmbeddedSimConfig | None = None, *, _backend: _Backend | None = None):
        self.cfg = cfg or EmbeddedSimConfig()
        self._backend = _backend or _Backend(self.cfg)
        self._backend.users += 1
        self._closed = False
        self._episode: EpisodeSpec | None = None
        self._city: City | None = None
        self._poses: list[Pose] = []
        self._collided: list[bool] = []
        self._done = False
        self._last_obs: Observation | None = None

    # --- scenes ------------------------------------------------------------------------------------------

    def sibling(self) -> EmbeddedSimulator:
        """Another simulator with its own episode state, sharing this one's GL context and cities."""
        return EmbeddedSimulator(self.cfg, _backend=self._backend)

    def register_city(self, city: City) -> None:
        """Make a hand-built `City` available under `city.scene_id` (to this simulator and its siblings)."""
        self._backend.registered[city.scene_id] = city

    def city(self, scene_id: str) -> City:
        """The city of `scene_id` (generated on first use and cached)."""
        return self._backend.city(scene_id)

    @property
    def renderer(self) -> CityRenderer:
        return self._backend.renderer

    # --- episode state -------------------------------------------------------------------------------------

    @property
    def pose(self) -> Pose:
        self._require_episode()
        return self._poses[-1]

    @property
    def poses(self) -> list[Pose]:
        """Poses visited in this episode, the start first (one more than steps taken)."""
        return list(self._poses)

    @property
    def collided(self) -> list[bool]:
        """Per step: did its motion segment collide."""
        return list(self._collided)

    @property
    def done(self) -> bool:
        return self._done

    def _require_episode(self) -> None:
        if self._closed:
            raise RuntimeError("this EmbeddedSimulator is closed")
        if self._episode is None:
            raise RuntimeError("no episode running: call reset(episode) first")

    # --- Simulator protocol -----------------------------------------------------------------------------

    def reset(self, episode: EpisodeSpec) -> Observation:
        """Start `episode` at its start pose and return the first observation."""
        return self.reset_batch([self], [episode])[0]

    def step(self, action_id: int) -> tuple[Observation, StepInfo]:
        """Execute one action; under collision policy `end` a colliding step leaves the pose unchanged."""
        return self.step_batch([self], [action_id])[0]

    def render(self, scene_id: str, pose: Pose, pitch_deg: float = 0.0) -> Observation:
        """A frame of `scene_id` from `pose`, without touching the episode state (used by the toolchain)."""
        return self.render_many(scene_id, [pose], pitch_deg)[0]

    def render_many(self, scene_id: str, poses: Sequence[Pose], pitch_deg: float | Sequence[float] = 0.0):
        """Frames of many poses of one scene (e.g. a trajectory), rendered in batches; no state change."""
        if self._closed:
            raise RuntimeError("this EmbeddedSimulator is closed")
        pitches = [float(pitch_deg)] * len(poses) if np.isscalar(pitch_deg) else [float(p) for p in pitch_deg]
        city = self._backend.city(scene_id)
        return self._backend.observe(
            [(city, pose, pitch) for pose, pitch in zip(poses, pitches, strict=True)]
        )

    # --- lockstep entry points (VectorSimulator) --------------------------------------------------------

    @staticmethod
    def reset_batch(sims: Sequence[EmbeddedSimulator], episodes: Sequence[EpisodeSpec]) -> list[Observation]:
        """`reset` of many simulators; the first frames are rendered together where they share a context."""
        starts = [sim._begin(episode) for sim, episode in zip(sims, episodes, strict=True)]
        return _observe_all(sims, starts)

    @staticmethod
    def step_batch(
        sims: Sequence[EmbeddedSimulator], actions: Sequence[int]
    ) -> list[tuple[Observation, StepInfo]]:
        """`step` of many simulators; frames are rendered together where they share a context."""
        moves = [sim._advance(int(a)) for sim, a in zip(sims, actions, strict=True)]
        observations = _observe_all(sims, [pose for _, pose in moves])
        return [(obs, info) for obs, (info, _) in zip(observations, moves)]

    def _begin(self, episode: EpisodeSpec) -> Pose:
        """Episode bookkeeping of `reset`; returns the start pose (to be rendered)."""
        if self._closed:
            raise RuntimeError("this EmbeddedSimulator is closed")
        self._city = self._backend.city(episode.scene_id)
        self._episode = episode
        start = Pose(*(float(v) for v in episode.start.as_array()))
        occupancy = self._city.occupancy(self.cfg.voxel_size)
        if start.z <= self._city.ground_z or occupancy.is_occupied(start.position[None])[0]:
            logger.warning(
                "episode %s starts inside an obstacle or the ground at %s", episode.episode_id, start
            )
        self._poses, self._collided, self._done = [start], [], False
        self._last_obs = None
        return start

    def _advance(self, action: int) -> tuple[StepInfo, Pose | None]:
        """Dynamics + collision of one step; returns its info and the new pose, or None if it did not move."""
        self._require_episode()
        if self._done:
            raise RuntimeError(
                f"episode {self._episode.episode_id} has ended (STOP or collision); call reset()"
            )
        motion = step_motion(self._poses[-1], action)
        collided = False
        if self.cfg.collision != "ignore":
            collided = motion_collides(self._city.occupancy(self.cfg.voxel_size), motion, self._city.ground_z)
        blocked = collided and self.cfg.collision == "end"
        pose = motion.start if blocked else motion.end
        self._done = action == C.ACTION_STOP or blocked
        self._poses.append(pose)
        self._collided.append(collided)
        extra = {
            "step": len(self._collided),
            "attempted_pose": motion.end,
            "out_of_bounds": not bool(self._city.bounds.contains(motion.end.position[None])[0]),
            "collisions": sum(self._collided),
        }
        info = StepInfo(action=action, collided=collided, done=self._done, extra=extra)
        return info, (None if pose == motion.start else pose)

    def close(self) -> None:
        """Release this simulator; the GL context goes when the last sibling closes."""
        if self._closed:
            return
        self._closed = True
        self._backend.users -= 1
        if self._backend.users == 0:
            self._backend.renderer.close()

    def __enter__(self) -> EmbeddedSimulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _observe_all(sims: Sequence[EmbeddedSimulator], poses: Sequence[Pose | None]) -> list[Observation]:
    """New observations where a pose is given (rendered per backend in batches), else each sim's last one."""
    by_backend: dict[int, list[int]] = {}
    for i, pose in enumerate(poses):
        if pose is not None:
            by_backend.setdefault(id(sims[i]._backend), []).append(i)
    for indices in by_backend.values():
        backend = sims[indices[0]]._backend
        requests = [(sims[i]._city, poses[i], sims[i]._episode.pitch_deg) for i in indices]
        for i, obs in zip(indices, backend.observe(requests)):
            sims[i]._last_obs = obs
    return [sim._last_obs for sim in sims]
