"""The one lockstep environment: `num_envs` simulators, stepped together, each slot restartable on its own.

`None` marks an idle slot: pass `None` as its episode or action, and get `None` back. A slot becomes idle when its
episode is done (STOP, a collision under an ending policy, or an engine error); `reset_env` refills it.
Simulators of one class that offers `reset_batch` / `step_batch` (the embedded one) render together; others
(bridges, blind simulators) are stepped one after the other, and an engine failure while stepping ends only the
episode it hit (as in the official evaluation, which scores it from the current pose).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

from openfly_agent.sim.base import EpisodeSpec, Observation, Simulator, StepInfo
from openfly_agent.sim.bridges.base import BridgeError
from openfly_agent.sim.embedded import EmbeddedSimulator

logger = logging.getLogger(__name__)

ERROR_KEY = "error"  # StepInfo.extra key holding the engine error message
# What an engine failure looks like: the bridges' error (after their one reconnect) or a socket / file error.
ENGINE_ERRORS = (BridgeError, OSError)


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
        self._running = [False] * len(self.sims)
        self._last: list[Observation | None] = [None] * len(self.sims)
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
        return list(self._running)

    def reset_env(self, index: int, episode: EpisodeSpec) -> Observation:
        """Start `episode` in slot `index` (whatever the slot was doing)."""
        obs = self.sims[index].reset(episode)
        self._running[index], self._last[index] = True, obs
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
        self._running = [False] * self.num_envs
        for i, obs in zip(started, observations):
            self._running[i], self._last[i], out[i] = True, obs, obs
        return out

    def step(self, actions: Sequence[int | None]) -> tuple[list[Observation | None], list[StepInfo | None]]:
        """Step every slot with an action; `None` (required for idle / done slots) skips a slot."""
        if len(actions) != self.num_envs:
            raise ValueError(f"step got {len(actions)} actions for {self.num_envs} environments")
        for i, action in enumerate(actions):
            if action is not None and not self._running[i]:
                raise ValueError(f"environment {i} has no running episode (it is idle or done); pass None")
        observations: list[Observation | None] = [None] * self.num_envs
        infos: list[StepInfo | None] = [None] * self.num_envs
        stepping = [i for i, action in enumerate(actions) if action is not None]
        if self._batched:
            sims = [self.sims[i] for i in stepping]
            results = type(self.sims[0]).step_batch(sims, [int(actions[i]) for i in stepping])
        else:
            results = [self._step_one(i, int(actions[i])) for i in stepping]
        for i, (obs, info) in zip(stepping, results):
            observations[i], infos[i] = obs, info
            self._last[i], self._running[i] = obs, not info.done
        return observations, infos

    def _step_one(self, index: int, action: int) -> tuple[Observation, StepInfo]:
        """Step one simulator; an engine failure ends its episode at the last pose (`extra[ERROR_KEY]`)."""
        try:
            return self.sims[index].step(action)
        except ENGINE_ERRORS as err:
            logger.warning("slot %d: simulator step failed (%s); ending its episode", index, err)
            info = StepInfo(action=action, done=True, extra={ERROR_KEY: f"{type(err).__name__}: {err}"})
            return self._last[index], info

    def close(self) -> None:
        """Close every simulator (each at most once)."""
        for sim in self.sims:
            sim.close()

    def __enter__(self) -> VectorSimulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
