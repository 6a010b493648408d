"""Step many episodes in lockstep: one `Simulator` per environment slot, stepped together.

`None` marks an idle slot: pass `None` as its episode or action, and get `None` back. A slot becomes
idle when its episode is done (STOP, or a collision under an ending policy); `reset_env` refills it.
Per-slot `EpisodeRecord`s hold what metrics need (poses, actions, collision flags, stop).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from openfly_agent import constants as C
from openfly_agent.sim.base import EpisodeSpec, Observation, Simulator, StepInfo
from openfly_agent.sim.embedded import EmbeddedSimulator
from openfly_agent.utils.geometry import Pose


@dataclass
class EpisodeRecord:
    """What happened in one episode of one slot."""

    episode_id: str
    scene_id: str
    poses: list[Pose] = field(default_factory=list)  # start first; one more than actions
    actions: list[int] = field(default_factory=list)
    collided: list[bool] = field(default_factory=list)
    done: bool = False

    @property
    def stopped(self) -> bool:
        return bool(self.actions) and self.actions[-1] == C.ACTION_STOP

    @property
    def collision_step(self) -> int | None:
        """Index (0-based) of the first colliding step, or None."""
        return self.collided.index(True) if any(self.collided) else None

    def positions(self) -> np.ndarray:
        """(T + 1, 3) visited positions, the start first."""
        return np.array([p.position for p in self.poses]).reshape(-1, 3)


class VectorSimulator:
    """Lockstep wrapper over `num_envs` simulators (built by `make_sim`, or given as `sims`)."""

    def __init__(
        self,
        make_sim: Callable[[], Simulator] | None = None,
        num_envs: int | None = None,
        *,
        sims: Sequence[Simulator] | None = None,
    ):
        if sims is None:
            if make_sim is None or num_envs is None or num_envs < 1:
                raise ValueError("VectorSimulator needs make_sim and num_envs >= 1, or a list of sims")
            sims = [make_sim() for _ in range(num_envs)]
        if not sims:
            raise ValueError("VectorSimulator needs at least one simulator")
        self.sims: list[Simulator] = list(sims)
        self.records: list[EpisodeRecord | None] = [None] * len(self.sims)
        # Simulators of one class that offers reset_batch / step_batch (the embedded one) render together.
        kind = type(self.sims[0])
        self._batched = all(type(s) is kind for s in self.sims) and hasattr(kind, "step_batch")

    @classmethod
    def embedded(cls, cfg=None, num_envs: int = 1, cities: Sequence = ()) -> VectorSimulator:
        """`num_envs` embedded simulators sharing one GL context and city cache; `cities` are registered."""
        first = EmbeddedSimulator(cfg)
        for city in cities:
            first.register_city(city)
        return cls(sims=[first] + [first.sibling() for _ in range(num_envs - 1)])

    @property
    def num_envs(self) -> int:
        return len(self.sims)

    @property
    def active(self) -> list[bool]:
        """Per slot: an episode is running and not done."""
        return [r is not None and not r.done for r in self.records]

    def reset_env(self, index: int, episode: EpisodeSpec) -> Observation:
        """Start `episode` in slot `index` (whatever the slot was doing)."""
        obs = self.sims[index].reset(episode)
        self.records[index] = EpisodeRecord(episode.episode_id, episode.scene_id, poses=[obs.pose])
        return obs

    def reset(self, episodes: Sequence[EpisodeSpec | None]) -> list[Observation | None]:
        """Start one episode per slot (`None` leaves a slot idle); len(episodes) must equal num_envs."""
        if len(episodes) != self.num_envs:
            raise ValueError(f"reset got {len(episodes)} episodes for {self.num_envs} environments")
        out: list[Observation | None] = [None] * self.num_envs
        started = [i for i, episode in enumerate(episodes) if episode is not None]
        if self._batched:
            sims = [self.sims[i] for i in started]
            observations = type(self.sims[0]).reset_batch(sims, [episodes[i] for i in started])
        else:
            observations = [self.sims[i].reset(episodes[i]) for i in started]
        self.records = [None] * self.num_envs
        for i, obs in zip(started, observations):
            self.records[i] = EpisodeRecord(episodes[i].episode_id, episodes[i].scene_id, poses=[obs.pose])
            out[i] = obs
        return out

    def step(self, actions: Sequence[int | None]) -> tuple[list[Observation | None], list[StepInfo | None]]:
        """Step every slot with an action; `None` (required for idle / done slots) skips a slot."""
        if len(actions) != self.num_envs:
            raise ValueError(f"step got {len(actions)} actions for {self.num_envs} environments")
        active = self.active
        for i, action in enumerate(actions):
            if action is not None and not active[i]:
                raise ValueError(f"environment {i} has no running episode (it is idle or done); pass None")
        observations: list[Observation | None] = [None] * self.num_envs
        infos: list[StepInfo | None] = [None] * self.num_envs
        stepping = [i for i, action in enumerate(actions) if action is not None]
        if self._batched:
            sims = [self.sims[i] for i in stepping]
            results = type(self.sims[0]).step_batch(sims, [int(actions[i]) for i in stepping])
        else:
            results = [self.sims[i].step(int(actions[i])) for i in stepping]
        for i, (obs, info) in zip(stepping, results):
            action = actions[i]
            record = self.records[i]
            record.poses.append(obs.pose)
            record.actions.append(int(action))
            record.collided.append(bool(info.collided))
            record.done = bool(info.done)
            observations[i], infos[i] = obs, info
        return observations, infos

    def close(self) -> None:
        """Close every simulator (each at most once)."""
        for sim in self.sims:
            sim.close()

    def __enter__(self) -> VectorSimulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
