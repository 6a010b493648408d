"""DAgger augmentation at generation time: roll out a policy, relabel every visited state with the A* expert.

A recovery episode starts where an A* route starts. For `max_policy_steps` the policy flies (the expert
with random action noise, or a trained agent); afterwards the expert flies to the goal. Every visited
state is labelled with the expert's next action from that state, so the labels teach recovery from the
policy's own mistakes. A policy action whose motion would hit the dilated map is replaced by the
expert's. The rollout runs through the rollout layer's `LockstepRunner` (one episode, a `FreeFlightSimulator`)
with the `ExpertLabelling` hook of toolchain/expert.py, the loop and hook that DAgger rounds use too.
The instruction is the one of the clean A* route. Unlike A* episodes, `positions[t + 1]`
follows the executed action, not the label `actions[t]` (that is the point of the relabelling).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.rollout.policy import OBS_EXPERT_ACTION, Policy, PolicyFeatures
from openfly_agent.rollout.runner import LockstepRunner, RolloutHook
from openfly_agent.sim.base import Simulator
from openfly_agent.sim.free_flight import FreeFlightSimulator, RenderFn
from openfly_agent.sim.vector import VectorSimulator
from openfly_agent.toolchain import filters
from openfly_agent.toolchain.actions import ActionSequence, sequence_category
from openfly_agent.toolchain.config import GenerateConfig
from openfly_agent.toolchain.expert import (
    EXPERT_FAILED,
    NO_STOP,
    POLICY_MOVES,
    AStarExpert,
    DaggerRollout,
    ExpertLabelling,
)
from openfly_agent.toolchain.pipeline import (
    PlannedTrajectory,
    PreparedScene,
    Rejected,
    UnitResult,
    WorkUnit,
    build_episode,
    instruction_request,
    plan_trajectory,
    route_episode,
)
from openfly_agent.toolchain.render import render_poses
from openfly_agent.utils.geometry import path_length


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
                actions.append(int(self.rng.choice(POLICY_MOVES)))
            else:
                actions.append(int(obs[OBS_EXPERT_ACTION]))
        return actions


def relabelled_rollout(
    policy: Policy,
    episode: Episode,
    expert: AStarExpert,
    max_policy_steps: int,
    max_steps: int,
    render: RenderFn | None = None,
    hooks: Sequence[RolloutHook] = (),
) -> DaggerRollout:
    """One episode flown from `episode`'s start through the `LockstepRunner` with the `ExpertLabelling` hook.

    The environment is one `FreeFlightSimulator` (the hook keeps moves off the dilated map); it renders through
    `render` only for a policy whose `features.frames` ask for frames, and only the first `max_policy_steps`
    states (the policy acts at no later one).

    Args:
        policy: any `Policy` (batched, called with one observation per step).
        episode: the route as a dataset episode (start pose, goal, scene, camera pitch; `route_episode`).
        expert: labels every visited state (its legs lead to the episode's goal).
        render: (scene id, pose, pitch) -> Observation; required when the policy reads frames.
        hooks: more runner hooks, after the labelling.
    Returns:
        the visited poses and the expert's label at each; the last label is STOP.
    Raises:
        Rejected: `dagger_expert_failed` (no plan from a visited state) or `dagger_max_steps` (no STOP within
            `max_steps` states).
    """
    if policy.features.frames and render is None:
        raise ValueError(f"policy {policy.name!r} reads frames: relabelled_rollout needs a render function")
    ended: list[DaggerRollout] = []
    labelling = ExpertLabelling(
        lambda _: expert,
        ended.append,
        max_policy_steps=max_policy_steps,
        max_steps=max_steps,
        label_in_observation=policy.features.expert_action,
    )
    sim = FreeFlightSimulator(render if policy.features.frames else None, render_steps=max_policy_steps)
    with VectorSimulator(sims=[sim]) as env:
        # the runner's cap is never met: the labelling ends a rollout at its (max_steps + 1)-th state
        runner = LockstepRunner(
            policy, env, max_steps + 1, [labelling, *hooks], whole_groups=False, show_progress=False
        )
        runner.run([episode], C.SPLIT_TRAIN)
    (rollout,) = ended
    if rollout.failed in (EXPERT_FAILED, NO_STOP):
        raise Rejected(rollout.failed, rollout.detail)
    if rollout.failed is not None:
        raise RuntimeError(f"dagger rollout of {episode.episode_id}: {rollout.detail}")
    return rollout


def leg_end_frames(legs: list[int], n_legs: int) -> list[int]:
    """Each leg's end frame from the expert's leg at every state (`DaggerRollout.legs`), in the A* episodes'
    convention (`leg_of_frame`): leg k ends at the first state of leg k + 1, the last leg at the last state (the
    STOP). E.g. legs [0, 0, 1, 1, 1] of 2 legs -> [2, 4]."""
    ends = []
    for k in range(n_legs - 1):
        later = [t for t, leg in enumerate(legs) if leg > k]
        if not later:
            raise ValueError(f"the rollout never left leg {k} of {n_legs} (legs {legs})")
        ends.append(later[0])
    return ends + [len(legs) - 1]


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
        rollout = relabelled_rollout(
            policy,
            route_episode(f"{scene_id}/dagger/{unit.index}", scene_id, planned),
            AStarExpert(prepared.astar, [leg.goal for leg in planned.route.legs]),
            cfg.dagger.max_policy_steps,
            cfg.dagger.max_steps,
            render=sim.render,
        )
        poses, labels = rollout.poses, rollout.labels
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
    leg_ends = leg_end_frames(rollout.legs, len(planned.route.legs))
    recovery = PlannedTrajectory(planned.route, seq, leg_ends, category, planned.pitch_deg, 0)
    rendered = render_poses(sim, scene_id, seq.poses, planned.pitch_deg, None, cfg.render.min_box_pixels)
    stats = {"plan_s": t1 - t0, "render_s": time.perf_counter() - t1}
    reason = filters.check_frames(rendered.frames, cfg.filters)
    if reason:
        return UnitResult(unit, reason=reason, stats=stats)
    episode = build_episode(unit, cfg.seed, scene_id, recovery, rendered, cfg.render.box_target)
    request = instruction_request(prepared, planned, clean, seed, cfg)
    stats.update(
        flight_height_m=float(planned.route.flight_z - prepared.pmap.elevation),
        path_length_m=float(path_length(seq.positions)),
        num_frames=len(episode),
    )
    return UnitResult(unit, episode=episode, frames=rendered.frames, request=request, stats=stats)
