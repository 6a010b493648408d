"""The A* expert and the one runner hook that labels every visited state with it (DAgger generation and rounds).

`AStarExpert` gives the next codebook action from any pose. `ExpertLabelling` is the `LockstepRunner` hook of
every DAgger rollout: it records each visited state with the expert's label, lets the policy fly its first
`max_policy_steps` states (the expert's label replaces a STOP, a lateral move, a move across the dilated map
and, with probability `expert_mix`, any move), then the expert flies; the expert's STOP ends the rollout.
The generation-time rollout (toolchain/dagger.py) and the rounds (toolchain/dagger_rounds.py) differ only in
its constructor arguments.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.rollout.legs import current_leg
from openfly_agent.rollout.policy import OBS_EXPERT_ACTION
from openfly_agent.rollout.runner import RolloutHook, RunningEpisode
from openfly_agent.sim import dynamics
from openfly_agent.toolchain.actions import merge_forward
from openfly_agent.toolchain.astar import ActionSpaceAStar, PlanningFailed
from openfly_agent.toolchain.config import BOX_TARGET_FINAL, BOX_TARGET_LEG, BOX_TARGETS
from openfly_agent.utils.geometry import Pose

# The policy's actions the expert lets it fly (STOP and the lateral moves are the expert's); in this order the
# noisy expert draws its random moves from them.
POLICY_MOVES = (
    C.ACTION_FORWARD,
    C.ACTION_TURN_LEFT,
    C.ACTION_TURN_RIGHT,
    C.ACTION_ASCEND,
    C.ACTION_DESCEND,
    C.ACTION_FORWARD_6,
    C.ACTION_FORWARD_9,
)
# Why a rollout has no usable end (`DaggerRollout.failed`); the first two are generation's rejection reasons.
EXPERT_FAILED = "dagger_expert_failed"  # the expert has no plan from a visited state
NO_STOP = "dagger_max_steps"  # no expert STOP within max_steps states
SIM_ENDED = "dagger_sim_ended"  # the simulator ended the episode (engine error, or a collision that ends)

_ROLLOUT, _EXPERT = "dagger_rollout", "dagger_expert"  # ExpertLabelling's keys in RunningEpisode.state


class AStarExpert:
    """Next codebook action from any pose: the first label of the A* plan to the current leg's goal.

    Legs are passed in order; reaching a leg's goal (within tolerance) moves on to the next one, STOP at
    the last. Plans are reused while the executed actions follow them (`reuse_plans`), re-planned after a
    deviation. `stop_radius_m` widens the last goal: STOP anywhere within that 3-D distance of it (the
    task counts a STOP within the success radius; 0 keeps the planner's tolerance).
    """

    def __init__(
        self,
        astar: ActionSpaceAStar,
        goals: list[np.ndarray],
        reuse_plans: bool = True,
        stop_radius_m: float = 0.0,
    ):
        self.astar, self.goals, self.leg = astar, [np.asarray(g, dtype=np.float64) for g in goals], 0
        self.reuse_plans = reuse_plans  # False: plan afresh at every pose (labels depend on the pose only)
        self.tolerance = astar.cfg.goal_tolerance_m
        self.stop_radius_m = max(float(stop_radius_m), self.tolerance)
        self._labels: list[int] = []
        self._poses: list[Pose] = []

    def action(self, pose: Pose) -> int:
        """Raises PlanningFailed when no plan exists from `pose`."""
        leg = current_leg(self.leg, pose.position, self.goals, self.tolerance)
        if leg != self.leg:  # a new leg: the plan to the previous goal is spent
            self.leg, self._labels, self._poses = leg, [], []
        if self._reached(pose, self.leg):
            return C.ACTION_STOP
        if not (self.reuse_plans and self._poses and self._poses[0] == pose):
            primitives = self.astar.plan(pose, self.goals[self.leg]).primitives
            if not primitives:  # within the planner's tolerance by its own float arithmetic
                return C.ACTION_STOP
            self._labels, _ = merge_forward(primitives)
            self._poses = dynamics.rollout(pose, self._labels)[:-1]
        self._poses.pop(0)
        return self._labels.pop(0)

    def _reached(self, pose: Pose, leg: int) -> bool:
        radius = self.stop_radius_m if leg == len(self.goals) - 1 else self.tolerance
        return float(np.linalg.norm(pose.position - self.goals[leg])) <= radius


@dataclass
class DaggerRollout:
    """One relabelled rollout: visited poses, the expert's label at each, frames and target boxes.

    `failed` is None for a rollout that ended with the expert's STOP, else why it has no usable end
    (`EXPERT_FAILED`, `NO_STOP` or `SIM_ENDED`, explained in `detail`).
    """

    source: Episode
    poses: list[Pose] = field(default_factory=list)
    labels: list[int] = field(default_factory=list)
    frames: list[np.ndarray] = field(default_factory=list)  # (H, W, 3) uint8; 1 x 1 without rendering
    boxes: list[np.ndarray | None] = field(default_factory=list)
    legs: list[int] = field(default_factory=list)  # the expert's leg at each state (0 .. legs - 1)
    agent_steps: int = 0  # states where the policy proposed the action
    failed: str | None = None
    detail: str = ""

    @property
    def stopped(self) -> bool:
        """The last recorded label is the expert's STOP."""
        return bool(self.labels) and self.labels[-1] == C.ACTION_STOP


class ExpertLabelling(RolloutHook):
    """The runner hook of a DAgger rollout: the A* expert labels every visited state and flies when the policy may not.

    Before the policy acts the current state is recorded with the expert's label; the expert's STOP, a state
    without a plan or a state beyond the first `max_steps` ends the rollout. The policy proposes the action for
    its first `max_policy_steps` states; the expert's label is flown instead with probability `expert_mix`, and
    whenever the proposed action is not one of `POLICY_MOVES` (STOP, a lateral move) or its motion would cross
    the dilated map (`astar.segment_blocked`). Every ended rollout goes to `on_rollout`, in completion order
    (`failed` set when it has no usable end).

    Args:
        make_expert: the A* expert of an episode (plans to its goal from any pose).
        on_rollout: called with each ended `DaggerRollout`.
        max_policy_steps: states the policy may fly at most before the expert takes over.
        max_steps: states at most; a rollout without the expert's STOP by then fails (`NO_STOP`).
        expert_mix: probability that the expert's action is flown instead of the policy's (drawn per proposed
            action; 0 draws nothing).
        box_target: the landmark whose box each state records, as the dataset's `render.box_target`: `final`
            (the episode's last target) or `leg` (the target of the expert's current leg; the expert needs one
            goal per target landmark).
        label_in_observation: add the label to the policy's observation (`OBS_EXPERT_ACTION`; for a policy with
            `features.expert_action`, such as the noisy expert).
        seed: seed of the expert-mix draws.
    """

    def __init__(
        self,
        make_expert: Callable[[Episode], AStarExpert],
        on_rollout: Callable[[DaggerRollout], None],
        *,
        max_policy_steps: int,
        max_steps: int,
        expert_mix: float = 0.0,
        label_in_observation: bool = False,
        seed: int = 0,
        box_target: str = BOX_TARGET_FINAL,
    ):
        if box_target not in BOX_TARGETS:
            raise ValueError(f"box_target must be one of {BOX_TARGETS}, got {box_target!r}")
        self.make_expert, self.on_rollout, self.box_target = make_expert, on_rollout, box_target
        self.max_policy_steps, self.max_steps = max_policy_steps, max_steps
        self.expert_mix, self.label_in_observation = expert_mix, label_in_observation
        self.rng = np.random.default_rng(seed)

    def on_episode_start(self, running: RunningEpisode) -> None:
        expert = self.make_expert(running.episode)
        targets = running.episode.landmark_ids
        if self.box_target == BOX_TARGET_LEG and len(targets) != len(expert.goals):
            raise ValueError(
                f"{running.episode.episode_id}: box_target 'leg' needs one expert goal per target landmark, "
                f"got {len(expert.goals)} goals for {len(targets)} targets"
            )
        running.state[_ROLLOUT] = DaggerRollout(running.episode)
        running.state[_EXPERT] = expert

    def before_act(self, running: RunningEpisode) -> bool:
        """Record the current state with the expert's label; True when the rollout ends here."""
        rollout, obs = running.state[_ROLLOUT], running.obs
        if len(rollout.labels) >= self.max_steps:  # the last of them was not a STOP
            rollout.failed, rollout.detail = NO_STOP, f"goal not reached in {self.max_steps} steps"
            return True
        expert = running.state[_EXPERT]
        try:
            # a state that reaches the current leg's goal moves the expert on to its next leg
            label = expert.action(obs.pose)
        except PlanningFailed as err:
            rollout.failed, rollout.detail = EXPERT_FAILED, str(err)
            return True
        rollout.poses.append(obs.pose)
        rollout.labels.append(int(label))
        rollout.legs.append(expert.leg)
        rollout.frames.append(np.ascontiguousarray(obs.rgb))
        if self.box_target == BOX_TARGET_LEG:
            box = running.landmark_box(running.episode.landmark_ids[expert.leg])
        else:
            box = running.target_box()
        rollout.boxes.append(None if box is None else np.asarray(box, dtype=np.float64))
        return rollout.stopped

    def asks_policy(self, running: RunningEpisode) -> bool:
        return running.state[_ROLLOUT].agent_steps < self.max_policy_steps

    def observation_fields(self, running: RunningEpisode) -> dict:
        return {OBS_EXPERT_ACTION: running.state[_ROLLOUT].labels[-1]} if self.label_in_observation else {}

    def choose_action(self, running: RunningEpisode, proposed: int | None) -> int:
        """The action flown from the current state: the policy's unless mixed out, not a policy move, or blocked."""
        rollout = running.state[_ROLLOUT]
        label = rollout.labels[-1]
        if proposed is None:  # the policy's budget is spent: the expert flies
            return label
        rollout.agent_steps += 1
        mixed = self.expert_mix > 0 and self.rng.random() < self.expert_mix
        if mixed or proposed not in POLICY_MOVES:
            return label
        pose = running.obs.pose
        blocked = running.state[_EXPERT].astar.segment_blocked(
            pose.position, dynamics.apply_action(pose, int(proposed)).position
        )
        return label if blocked else int(proposed)

    def on_episode_end(self, running: RunningEpisode) -> None:
        record = running.record
        rollout = running.state.get(_ROLLOUT) or DaggerRollout(running.episode)  # no state: the reset failed
        if rollout.failed is None and not rollout.stopped:
            rollout.failed = SIM_ENDED
            rollout.detail = (
                f"ended by the simulator ({record.end_reason}{': ' + record.error if record.error else ''})"
            )
        self.on_rollout(rollout)
