"""Baseline policies run through the same closed-loop runner as the agent.

- `random`: at every step an action drawn uniformly from the 10 model actions (STOP included, so an
  episode lasts 10 steps on average), from a generator seeded by (seed, episode id): the actions of an
  episode do not depend on the batch it runs in.
- `stop`: STOP at the first step (scored from the start pose).
- `forward`: `forward` (3 m) at every step until the step cap; never stops.
- `oracle`: the episode's ground-truth actions (`episodes.oracle_actions`), ending with STOP.
- `box_servo`: the reflex reference policy on the true target box (eval/box_servo.py; embedded simulator only).
"""

from __future__ import annotations

import hashlib

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.eval.box_servo import BoxServoPolicy, BoxServoSettings
from openfly_agent.eval.episodes import oracle_actions, oracle_replays_exactly
from openfly_agent.rollout.policy import OBS_EPISODE_ID, OBS_STEP, PolicyFeatures

BASELINE_NAMES = ("random", "stop", "forward", "oracle", "box_servo")
ORACLE_MODES = ("auto", "replay", "teleport")


def episode_seed(seed: int, episode_id: str) -> np.random.SeedSequence:
    """A seed sequence from the run seed and a stable hash of the episode id (independent of batching)."""
    digest = int.from_bytes(hashlib.sha256(episode_id.encode("utf-8")).digest()[:8], "little")
    return np.random.SeedSequence([int(seed), digest])


class RandomPolicy:
    """Uniform over the 10 model actions at every step, seeded per episode."""

    name = "random"
    features = PolicyFeatures(frames=False)

    def __init__(self, seed: int = 0):
        self.seed = int(seed)
        self._rngs: dict[str, np.random.Generator] = {}

    def reset(self, episode_ids: list[str]) -> None:
        for episode_id in episode_ids:
            self._rngs[episode_id] = np.random.default_rng(episode_seed(self.seed, episode_id))

    def act(self, observations: list[dict]) -> list[int]:
        actions = []
        for obs in observations:
            episode_id = obs[OBS_EPISODE_ID]
            if episode_id not in self._rngs:
                self.reset([episode_id])
            actions.append(int(self._rngs[episode_id].integers(0, C.NUM_ACTIONS)))
        return actions


class ConstantPolicy:
    """The same action at every step: `stop` (STOP at once) or `forward` (3 m forward until the cap)."""

    features = PolicyFeatures(frames=False)

    def __init__(self, name: str, action: int):
        self.name = name
        self.action = int(action)

    def reset(self, episode_ids: list[str]) -> None:
        return None

    def act(self, observations: list[dict]) -> list[int]:
        return [self.action] * len(observations)


class OraclePolicy:
    """Replays each episode's ground-truth actions (`oracle_actions`), then STOP.

    Args:
        episodes: the episodes it may be asked about.
        mode: `replay` (always replay actions), `teleport` (never; the runner follows the ground-truth poses)
            or `auto` (replay where `oracle_replays_exactly`, teleport elsewhere).
    """

    name = "oracle"
    features = PolicyFeatures(frames=False)

    def __init__(self, episodes: list[Episode], mode: str = "auto"):
        if mode not in ORACLE_MODES:
            raise ValueError(f"oracle mode {mode!r} is not one of {ORACLE_MODES}")
        self.mode = mode
        self._actions = {e.episode_id: oracle_actions(e) for e in episodes}
        self._replays = {e.episode_id: self._decide_replay(e) for e in episodes}

    def _decide_replay(self, episode: Episode) -> bool:
        if self.mode == "auto":
            return oracle_replays_exactly(episode)
        return self.mode == "replay"

    def replays(self, episode_id: str) -> bool:
        """True when `episode_id` runs through the simulator, False when it is teleported along its poses."""
        return self._replays[episode_id]

    def reset(self, episode_ids: list[str]) -> None:
        return None

    def act(self, observations: list[dict]) -> list[int]:
        out = []
        for obs in observations:
            actions = self._actions.get(obs[OBS_EPISODE_ID])
            if actions is None:
                raise KeyError(f"oracle: episode {obs[OBS_EPISODE_ID]!r} was not given to the oracle")
            step = int(obs[OBS_STEP])
            out.append(actions[step] if step < len(actions) else C.ACTION_STOP)
        return out


def make_baseline(
    name: str,
    episodes: list[Episode],
    seed: int = 0,
    oracle_mode: str = "auto",
    box_servo: BoxServoSettings | None = None,
):
    """Build the baseline called `name` (one of BASELINE_NAMES)."""
    if name == "random":
        return RandomPolicy(seed)
    if name == "stop":
        return ConstantPolicy("stop", C.ACTION_STOP)
    if name == "forward":
        return ConstantPolicy("forward", C.ACTION_FORWARD)
    if name == "oracle":
        return OraclePolicy(episodes, oracle_mode)
    if name == "box_servo":
        return BoxServoPolicy(box_servo)
    raise ValueError(
        f"unknown baseline {name!r}; choose one of {BASELINE_NAMES} "
        "(or 'agent' / 'agent_true_box' with a checkpoint)"
    )
