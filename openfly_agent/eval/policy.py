"""The policy protocol the closed-loop runner drives: the agent and every baseline implement it.

A policy sees one observation dict per running episode (`episode_id`, `instruction`, `rgb`, `pose`,
`step`) and returns one action id 0..9 per episode, batched; `reset` starts fresh episodes. Policies
that predict more per step (the agent's landmark box and keyframe decisions) expose it through
`step_details`, which the runner writes to the per-episode log.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from openfly_agent import constants as C

OBS_EPISODE_ID = C.EPISODE_ID
OBS_STEP = "step"  # int, number of actions already taken in the episode


@runtime_checkable
class Policy(Protocol):
    """Batched closed-loop policy.

    Attributes:
        name: short name used for output folders and tables.
        needs_frames: False for policies that never look at `rgb` (the runner may then skip frame copies).
    """

    name: str
    needs_frames: bool

    def reset(self, episode_ids: list[str]) -> None:
        """Forget everything about `episode_ids` (they start now or have just finished)."""
        ...

    def act(self, observations: list[dict]) -> list[int]:
        """One action id (0..9) per observation, in order."""
        ...


def step_details(policy: Policy, episode_ids: list[str]) -> list[dict]:
    """What `policy` predicted besides the action at its last `act` call, one dict per episode id.

    Policies may implement `step_details(episode_ids) -> list[dict]` (keys `box`: (cx, cy, w, h) or None,
    `keyframes`: the keyframe sets in memory); for the others every dict is empty.
    """
    method = getattr(policy, "step_details", None)
    if method is None:
        return [{} for _ in episode_ids]
    details = method(episode_ids)
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
