"""Embedded scenes without rendering, for policies that never look at frames (stop, forward, random, oracle).

`BlindEmbeddedSimulator` moves and checks collisions exactly as `EmbeddedSimulator` with
`collision="count"` (same `sim/dynamics.py` step, same `sim/collision.motion_collides` against the same
city occupancy), but returns a 1 x 1 black frame instead of rendering. Baselines then cost no GL time;
a test checks that their records equal those from the rendering simulator.
"""

from __future__ import annotations

from openfly_agent import constants as C
from openfly_agent.sim.base import NO_FRAME, EpisodeSpec, Observation, StepInfo
from openfly_agent.sim.city import City, generate_city, parse_scene_id
from openfly_agent.sim.collision import motion_collides
from openfly_agent.sim.dynamics import step_motion
from openfly_agent.sim.embedded import EmbeddedSimConfig
from openfly_agent.utils.geometry import Pose


class CityCache:
    """Cities of `embedded-<seed>` scenes built with one `CityConfig`, shared by several simulators."""

    def __init__(self, cfg: EmbeddedSimConfig):
        self.cfg = cfg
        self._cities: dict[str, City] = {}

    def __call__(self, scene_id: str) -> City:
        if scene_id not in self._cities:
            self._cities[scene_id] = generate_city(parse_scene_id(scene_id), self.cfg.city)
        return self._cities[scene_id]


class BlindEmbeddedSimulator:
    """The `Simulator` protocol over embedded cities with collisions counted, and no frames."""

    def __init__(self, cfg: EmbeddedSimConfig, cities: CityCache | None = None):
        self.cfg = cfg
        self.cities = cities or CityCache(cfg)
        self._city: City | None = None
        self._pose: Pose | None = None
        self._done = True

    def reset(self, episode: EpisodeSpec) -> Observation:
        """Start at the episode's start pose (1 x 1 black frame)."""
        self._city = self.cities(episode.scene_id)
        self._pose = Pose(*(float(v) for v in episode.start.as_array()))
        self._done = False
        return Observation(rgb=NO_FRAME, pose=self._pose, boxes={})

    def step(self, action_id: int) -> tuple[Observation, StepInfo]:
        """Move through `sim/dynamics.py`; `collided`: the segment hits the city or the ground (counted)."""
        if self._pose is None or self._done:
            raise RuntimeError("BlindEmbeddedSimulator.step() needs a running episode: call reset() first")
        motion = step_motion(self._pose, int(action_id))
        collided = motion_collides(self._city.occupancy(self.cfg.voxel_size), motion, self._city.ground_z)
        self._pose = motion.end
        self._done = int(action_id) == C.ACTION_STOP
        return Observation(rgb=NO_FRAME, pose=self._pose, boxes={}), StepInfo(
            action=int(action_id), collided=bool(collided), done=self._done
        )

    def close(self) -> None:
        self._pose = None
