"""The one policy protocol the lockstep runner drives: the agent, every baseline and DAgger's policies.

A policy sees one observation dict per running episode (`episode_id`, `instruction`, `rgb`, `pose`, `step`, and
what its declared `features` ask for) and returns one action id 0..9 per episode, batched; `reset` starts fresh
episodes. What a policy needs beyond that is declared in `features`, never probed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from openfly_agent import constants as C

OBS_EPISODE_ID = C.EPISODE_ID
OBS_STEP = "step"  # int, number of actions already taken in the episode
OBS_TARGET_BOX = "target_box"  # (cx, cy, w, h) of the target landmark in the frame, or None when not visible
OBS_EXPERT_ACTION = "expert_action"  # int, the A* expert's label of the current state (DAgger only)


@dataclass(frozen=True)
class PolicyFeatures:
    """What a policy needs from the loop and what it gives back besides the action.

    Attributes:
        frames: `act` reads `rgb` (False: a blind simulator may serve it, and no frame is rendered).
        target_box: observations carry the simulator's true box of the target landmark (`target_box`).
        expert_action: observations carry the expert's label of the state (`expert_action`; DAgger loops).
        step_details: the policy implements `step_details(episode_ids)` (predicted box, keyframes).
    """

    frames: bool = True
    target_box: bool = False
    expert_action: bool = False
    step_details: bool = False


class Policy(Protocol):
    """Batched closed-loop policy.

    Attributes:
        name: short name used for output folders and tables.
        features: what it needs and gives (`PolicyFeatures`).
    """

    name: str
    features: PolicyFeatures

    def reset(self, episode_ids: list[str]) -> None:
        """Forget everything about `episode_ids` (they start now or have just finished)."""
        ...

    def act(self, observations: list[dict]) -> list[int]:
        """One action id (0..9) per observation, in order."""
        ...

    def step_details(self, episode_ids: list[str]) -> list[dict]:
        """Only with `features.step_details`: what `act` predicted besides the action, one dict per episode id
        (`box`: (cx, cy, w, h) or None; `keyframes`: the keyframe sets in memory)."""
        ...


def step_details(policy: Policy, episode_ids: list[str]) -> list[dict]:
    """`policy.step_details(episode_ids)` when it declares them, else one empty dict per episode."""
    if not policy.features.step_details:
        return [{} for _ in episode_ids]
    details = policy.step_details(episode_ids)
    if len(details) != len(episode_ids):
        raise ValueError(
            f"policy {policy.name!r}: step_details returned {len(details)} entries "
            f"for {len(episode_ids)} episodes"
        )
    return [dict(d or {}) for d in details]


def check_actions(policy_name: str, actions: list[int], expected: int) -> list[int]:
    """Validate a policy's output: `expected` ints in 0..9; raises a ValueError that names the policy."""
    if len(actions) != expected:
        raise ValueError(
            f"policy {policy_name!r} returned {len(actions)} actions for {expected} observations"
        )
    out = []
    for action in actions:
        action = int(action)
        if action not in C.MODEL_ACTION_IDS:
            raise ValueError(
                f"policy {policy_name!r} returned action {action}; valid ids are 0..{C.NUM_ACTIONS - 1}"
            )
        out.append(action)
    return out
