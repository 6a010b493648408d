"""A simulator without a world: poses move by `sim/dynamics.py`, nothing collides, frames come from a callback.

`FreeFlightSimulator` is what a caller uses that keeps its own obstacle check (the toolchain's DAgger generation
replaces a move that would cross its dilated planning map before the step is executed): every action is flown
as commanded. With a `render` callback each visited pose is rendered through it (e.g. `EmbeddedSimulator.render`),
or only the first `render_steps` poses of an episode (those a policy may still act at, when the caller knows);
otherwise the observations carry a 1 x 1 black frame and no boxes, so a policy that never looks at frames costs
no rendering.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

from openfly_agent import constants as C
from openfly_agent.sim.base import NO_FRAME, EpisodeSpec, Observation, StepInfo
from openfly_agent.sim.dynamics import apply_action
from openfly_agent.utils.geometry import Pose

# (scene_id, pose, pitch_deg) -> the observation at that pose, e.g. `EmbeddedSimulator.render`
RenderFn = Callable[[str, Pose, float], Observation]


class FreeFlightSimulator:
    """The `Simulator` protocol by `sim/dynamics.py` alone: no collisions, STOP ends the episode.

    Args:
        render: called once per visited pose with (scene id, pose, camera pitch); None: no frames.
        render_steps: render only the first `render_steps` poses of each episode (None: all of them).
    """

    def __init__(self, render: RenderFn | None = None, render_steps: int | None = None):
        self.render, self.render_steps = render, render_steps
        self._episode: EpisodeSpec | None = None
        self._pose: Pose | None = None
        self._visited = 0  # poses of the running episode so far, the current one included
        self._done = True

    def reset(self, episode: EpisodeSpec) -> Observation:
        """Start at the episode's start pose."""
        self._episode, self._pose, self._visited, self._done = episode, episode.start, 0, False
        return self._observe()

    def step(self, action_id: int) -> tuple[Observation, StepInfo]:
        """Move by `sim/dynamics.apply_action`; never `collided`, `done` after STOP."""
        if self._pose is None or self._done:
            raise RuntimeError("FreeFlightSimulator.step() needs a running episode: call reset() first")
        self._pose = apply_action(self._pose, int(action_id))
        self._done = int(action_id) == C.ACTION_STOP
        return self._observe(), StepInfo(action=int(action_id), done=self._done)

    def _observe(self) -> Observation:
        self._visited += 1
        if self.render is None or (self.render_steps is not None and self._visited > self.render_steps):
            return Observation(rgb=NO_FRAME, pose=self._pose, boxes={})
        obs = self.render(self._episode.scene_id, self._pose, self._episode.pitch_deg)
        return replace(obs, pose=self._pose)

    def close(self) -> None:
        self._episode = self._pose = None
