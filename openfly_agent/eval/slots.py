"""Lockstep environments with independently restartable slots, over any simulator.

The runner keeps a group of up to `num_slots` episodes in flight and starts the next group when the last
episode of the current one has finished. `SimulatorSlots` drives one `Simulator` per slot (bridges, or embedded
simulators); `VectorSlots` drives the embedded `VectorSimulator`, which steps all its environments in
one call. Engine failures while stepping end only the episode they hit (as in the official
evaluation, which scores it from the current pose).
"""

from __future__ import annotations

import logging
from typing import Protocol

from openfly_agent.sim.base import EpisodeSpec, Observation, Simulator, StepInfo
from openfly_agent.sim.bridges.base import BridgeError

logger = logging.getLogger(__name__)

ERROR_KEY = "error"  # StepInfo.extra key holding the engine error message
# What an engine failure looks like: the bridges' error (after their one reconnect) or a socket / file error.
ENGINE_ERRORS = (BridgeError, OSError)


class SlotEnv(Protocol):
    """`num_slots` environments stepped together; `None` actions leave a slot untouched."""

    num_slots: int

    def reset_slot(self, slot: int, spec: EpisodeSpec) -> Observation:
        """Start `spec` in `slot` (whatever the slot was doing) and return its first observation."""
        ...

    def step(self, actions: list[int | None]) -> tuple[list[Observation | None], list[StepInfo | None]]:
        """One action per slot (`None` leaves the slot alone); per slot (observation, info), or None."""
        ...

    def close(self) -> None:
        """Release the simulators."""
        ...


class SimulatorSlots:
    """One `Simulator` per slot, stepped one after the other."""

    def __init__(self, sims: list[Simulator]):
        if not sims:
            raise ValueError("SimulatorSlots needs at least one simulator")
        self.sims = list(sims)
        self.num_slots = len(self.sims)
        self._last: list[Observation | None] = [None] * self.num_slots

    def reset_slot(self, slot: int, spec: EpisodeSpec) -> Observation:
        obs = self.sims[slot].reset(spec)
        self._last[slot] = obs
        return obs

    def step(self, actions: list[int | None]) -> tuple[list[Observation | None], list[StepInfo | None]]:
        observations: list[Observation | None] = [None] * self.num_slots
        infos: list[StepInfo | None] = [None] * self.num_slots
        for slot, action in enumerate(actions):
            if action is None:
                continue
            try:
                observations[slot], infos[slot] = self.sims[slot].step(int(action))
            except ENGINE_ERRORS as err:
                logger.warning("slot %d: simulator step failed (%s); ending its episode", slot, err)
                observations[slot] = self._last[slot]
                infos[slot] = StepInfo(
                    action=int(action), done=True, extra={ERROR_KEY: f"{type(err).__name__}: {err}"}
                )
            self._last[slot] = observations[slot]
        return observations, infos

    def close(self) -> None:
        for sim in self.sims:
            sim.close()


class VectorSlots:
    """Slots over a lockstep `VectorSimulator` (`reset(list[EpisodeSpec])`, `step(list[int | None])`).

    Restarting one slot resets only that environment: the vector simulator is given `None` for the
    others when it supports partial resets (`reset_env(index, spec)`), otherwise its sub-simulator is
    reset directly.
    """

    def __init__(self, vector_sim):
        self.vector = vector_sim
        self.num_slots = int(getattr(vector_sim, "num_envs", None) or len(vector_sim.sims))

    def reset_slot(self, slot: int, spec: EpisodeSpec) -> Observation:
        if hasattr(self.vector, "reset_env"):
            return self.vector.reset_env(slot, spec)
        return self.vector.sims[slot].reset(spec)

    def step(self, actions: list[int | None]) -> tuple[list[Observation | None], list[StepInfo | None]]:
        observations, infos = self.vector.step(list(actions))
        return list(observations), list(infos)

    def close(self) -> None:
        self.vector.close()
