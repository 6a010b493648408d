"""DAgger augmentation: roll out a policy, relabel every visited state with the A* expert's next action.

A recovery episode starts where an A* route starts. For `max_policy_steps` the policy flies (the expert
with random action noise, or a trained agent); afterwards the expert flies to the goal. Every visited
state is labelled with the expert's next action from that state, so the labels teach recovery from the
policy's own mistakes. A policy action whose motion would hit the dilated map is replaced by the
expert's. The instruction is the one of the clean A* route. Unlike A* episodes, `positions[t + 1]`
follows the executed action, not the label `actions[t]` (that is the point of the relabelling).
"""

from __future__ import annotations

import time

import numpy as np

from openfly_agent import constants as C
from openfly_agent.rollout.policy import OBS_EPISODE_ID, OBS_EXPERT_ACTION, OBS_STEP, Policy, PolicyFeatures
from openfly_agent.sim import dynamics
from openfly_agent.sim.base import Simulator
from openfly_agent.toolchain import filters
from openfly_agent.toolchain.actions import ActionSequence, merge_forward, sequence_category
from openfly_agent.toolchain.astar import ActionSpaceAStar, PlanningFailed
from openfly_agent.toolchain.config import GenerateConfig
from openfly_agent.toolchain.pipeline import (
    PlannedTrajectory,
    PreparedScene,
    Rejected,
    UnitResult,
    WorkUnit,
    build_episode,
    instruction_request,
    plan_trajectory,
)
from openfly_agent.toolchain.render import render_poses
from openfly_agent.utils.geometry import Pose, path_length

NOISE_ACTIONS = (
    C.ACTION_FORWARD,
    C.ACTION_TURN_LEFT,
    C.ACTION_TURN_RIGHT,
    C.ACTION_ASCEND,
    C.ACTION_DESCEND,
    C.ACTION_FORWARD_6,
    C.ACTION_FORWARD_9,
)


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
        while self.leg < len(self.goals) - 1 and self._reached(pose, self.leg):
            self.leg, self._labels, self._poses = self.leg + 1, [], []
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


class NoisyExpertPolicy:
    """The expert's action (given in each observation), replaced by a random move with probability `noise_prob`."""

    name = "noisy_expert"
    features = PolicyFeatures(frames=False, expert_action=True)

    def __init__(self, noise_prob: float, rng: np.random.Generator):
        self.noise_prob, self.rng = noise_prob, rng

    def reset(self, episode_ids: list[str]) -> None:
        pass

    def act(self, observations: list[dict]) -> list[int]:
        actions = []
        for obs in observations:
            if self.rng.random() < self.noise_prob:
                actions.append(int(self.rng.choice(NOISE_ACTIONS)))
            else:
                actions.append(int(obs[OBS_EXPERT_ACTION]))
        return actions


def rollout_with_relabel(
    expert: AStarExpert,
    policy: Policy,
    start: Pose,
    observe,
    max_policy_steps: int,
    max_steps: int,
    episode_id: str = "",
    instruction: str = "",
) -> tuple[list[Pose], list[int]]:
    """Visited poses and the expert's label at each; the last label is STOP.

    One episode flown pose by pose through `sim/dynamics.py` (no simulator state; frames are rendered only for a
    policy whose features ask for them), so the toolchain's workers need no lockstep environment.

    Args:
        policy: any `Policy` (batched, called with one observation), already reset for `episode_id`.
        observe: pose -> Observation (called only when the policy needs frames).
    Raises:
        Rejected: the expert has no plan from a visited state, or the goal is not reached in `max_steps`.
    """
    pose, poses, labels = start, [], []
    for step in range(max_steps):
        try:
            label = expert.action(pose)
        except PlanningFailed as err:
            raise Rejected("dagger_expert_failed", str(err)) from None
        poses.append(pose)
        labels.append(label)
        if label == C.ACTION_STOP:
            return poses, labels
        executed = label
        if step < max_policy_steps:
            obs = {
                OBS_EPISODE_ID: episode_id,
                C.OBS_INSTRUCTION: instruction,
                C.OBS_RGB: observe(pose).rgb if policy.features.frames else np.zeros((1, 1, 3), np.uint8),
                C.OBS_POSE: pose.as_array(),
                OBS_STEP: step,
            }
            if policy.features.expert_action:
                obs[OBS_EXPERT_ACTION] = label
            executed = int(policy.act([obs])[0])
        if executed not in NOISE_ACTIONS:  # STOP, lateral moves or junk: the expert flies this step
            executed = label
        nxt = dynamics.apply_action(pose, executed)
        if expert.astar.segment_blocked(pose.position, nxt.position):
            nxt = dynamics.apply_action(pose, label)
        pose = nxt
    raise Rejected("dagger_max_steps", f"goal not reached in {max_steps} steps")


def generate_dagger_unit(
    prepared: PreparedScene, sim: Simulator, unit: WorkUnit, cfg: GenerateConfig, policy: Policy | None = None
) -> UnitResult:
    """One recovery episode: clean A* route (for the instruction), then the relabelled policy rollout."""
    seed = unit.seed(cfg.seed)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    scene_id = prepared.scene.scene_id
    try:
        planned = plan_trajectory(prepared, rng, cfg, allow_updown=False)
        policy = policy or NoisyExpertPolicy(cfg.dagger.noise_prob, rng)
        episode_id = f"{scene_id}/dagger/{unit.index}"
        policy.reset([episode_id])
        expert = AStarExpert(prepared.astar, [leg.goal for leg in planned.route.legs])
        poses, labels = rollout_with_relabel(
            expert,
            policy,
            planned.route.start,
            lambda p: sim.render(scene_id, p, planned.pitch_deg),
            cfg.dagger.max_policy_steps,
            cfg.dagger.max_steps,
            episode_id,
        )
        seq = ActionSequence(
            actions=np.asarray(labels, dtype=np.int64),
            raw_index=np.arange(len(labels), dtype=np.int64),
            positions=np.array([p.position for p in poses]),
            yaws=np.array([p.yaw for p in poses]),
        )
        for reason in (
            filters.check_action_count(seq.actions, cfg.filters),
            filters.check_height(seq.positions, seq.actions, prepared.pmap.elevation, prepared.tree_height_m),
        ):
            if reason:
                raise Rejected(reason)
    except Rejected as err:
        return UnitResult(unit, reason=err.reason, stats={"plan_s": time.perf_counter() - t0})
    t1 = time.perf_counter()
    clean = render_poses(sim, scene_id, planned.seq.poses, planned.pitch_deg, planned.seq.actions)
    category = sequence_category(seq, prepared.pmap.elevation, cfg.categories)
    recovery = PlannedTrajectory(planned.route, seq, [len(seq) - 1], category, planned.pitch_deg, 0)
    rendered = render_poses(sim, scene_id, seq.poses, planned.pitch_deg, None, cfg.render.min_box_pixels)
    stats = {"plan_s": t1 - t0, "render_s": time.perf_counter() - t1}
    reason = filters.check_frames(rendered.frames, cfg.filters)
    if reason:
        return UnitResult(unit, reason=reason, stats=stats)
    episode = build_episode(unit, cfg.seed, scene_id, recovery, rendered)
    request = instruction_request(prepared, planned, clean, seed, cfg)
    stats.update(
        flight_height_m=float(planned.route.flight_z - prepared.pmap.elevation),
        path_length_m=float(path_length(seq.positions)),
        num_frames=len(episode),
    )
    return UnitResult(unit, episode=episode, frames=rendered.frames, request=request, stats=stats)
