"""Navigation metrics (NE, SR, OSR, SPL, nDTW, collisions) as pure functions over trajectories.

A rollout becomes an `EpisodeTrajectory`; `episode_metrics` scores it under one `MetricProfile`
(rollout/profiles.py) and `aggregate` averages per scene and overall. Formulas: docs/METRICS.md.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from openfly_agent import constants as C
from openfly_agent.rollout.profiles import DEFAULT_PROFILE_NAMES, MetricProfile, get_profile
from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.rollout.stats import bootstrap_mean_interval, wilson_interval
from openfly_agent.sim.dynamics import rollout_array
from openfly_agent.utils.geometry import Pose, path_length

# Per-episode keys averaged by `aggregate`: metric key -> (summary key, scale).
_MEAN_KEYS = {
    "ne": ("ne_m", 1.0),
    "success": ("sr_pct", 100.0),
    "oracle_success": ("osr_pct", 100.0),
    "spl": ("spl_pct", 100.0),
    "ndtw": ("ndtw_pct", 100.0),
    "sdtw": ("sdtw_pct", 100.0),
    "path_length": ("path_length_m", 1.0),
    "steps": ("steps", 1.0),
    "stopped": ("stop_rate_pct", 100.0),
    "collided": ("collision_rate_pct", 100.0),
    "num_collisions": ("collisions_per_episode", 1.0),
    "early_stop": ("early_stop_pct", 100.0),
    "stopped_far": ("stopped_far_pct", 100.0),
    "stopped_after_passing": ("stopped_after_passing_pct", 100.0),
    "ended_by_collision": ("collision_end_pct", 100.0),
    "step_limit": ("step_limit_pct", 100.0),
}
# How an episode ends; exactly one per episode, so their rates sum to 100 % (with SR as "success").
OUTCOMES = ("success", "early_stop", "stopped_far", "stopped_after_passing", "collision_end", "step_limit")
EARLY_STOP_STEPS = 3  # a failed STOP among the first this many actions is an "early_stop"
# 95 % intervals of each summary: rate key -> (its interval key, the per-episode flag counted);
# mean key -> (its interval key, the per-episode value, scale). rollout/stats.py, docs/METRICS.md.
_RATE_INTERVALS = {"sr_pct": ("sr_ci95", "success"), "osr_pct": ("osr_ci95", "oracle_success")}
_MEAN_INTERVALS = {"spl_pct": ("spl_ci95", "spl", 100.0), "ne_m": ("ne_ci95", "ne", 1.0)}
INTERVAL_KEYS = {
    key: spec[0] for key, spec in (_RATE_INTERVALS | _MEAN_INTERVALS).items()
}  # summary key -> its interval


def _points(value, name: str, episode_id: str, min_rows: int = 1) -> np.ndarray:
    """(N, >=3) array-like -> (N, 3) float64; a 4th column (yaw) is dropped."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] < 3 or arr.shape[0] < min_rows:
        raise ValueError(
            f"episode {episode_id}: {name} must have shape (N >= {min_rows}, 3) (x, y, z [, yaw]), "
            f"got {arr.shape}"
        )
    if not np.isfinite(arr[:, :3]).all():
        raise ValueError(f"episode {episode_id}: {name} holds non-finite values")
    return arr[:, :3].copy()


@dataclass
class EpisodeTrajectory:
    """One evaluated rollout, in world metres.

    `positions[0]` is the start and `positions[t + 1]` the position after action t (a STOP repeats
    the position), i.e. what `sim.dynamics.rollout` returns; a 4th yaw column is accepted and dropped.
    `stop_step` is the index of the STOP action (`stopped=True` alone means the last action), and
    `collision_step` the index of the first action whose motion collided (`collision_steps` lists all
    of them when the rollout went on after a collision).
    """

    episode_id: str
    scene_id: str
    positions: np.ndarray  # (T + 1, 3)
    goal: np.ndarray  # (3,) the official goal is the last ground-truth position
    reference_path: np.ndarray  # (G, 3) ground-truth positions, start first
    stopped: bool = False
    stop_step: int | None = None
    collision_step: int | None = None
    collision_steps: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        eid = self.episode_id
        self.positions = _points(self.positions, "positions", eid)
        self.goal = _points(np.reshape(self.goal, (1, -1)), "goal", eid)[0]
        self.reference_path = _points(self.reference_path, "reference_path", eid)
        num_actions = len(self.positions) - 1
        if self.stop_step is not None:
            self.stopped = True
        elif self.stopped:
            if num_actions < 1:
                raise ValueError(f"episode {eid}: stopped=True but positions hold no action (only the start)")
            self.stop_step = num_actions - 1
        if self.stop_step is not None and not 0 <= self.stop_step < num_actions:
            raise ValueError(f"episode {eid}: stop_step {self.stop_step} outside the {num_actions} actions")
        steps = set(self.collision_steps or ())
        if self.collision_step is not None:
            steps.add(self.collision_step)
        self.collision_steps = tuple(sorted(int(s) for s in steps))
        self.collision_step = self.collision_steps[0] if self.collision_steps else None
        for step in self.collision_steps:
            if not 0 <= step < num_actions:
                raise ValueError(f"episode {eid}: collision step {step} outside the {num_actions} actions")
            if self.stop_step is not None and step >= self.stop_step:
                raise ValueError(
                    f"episode {eid}: collision step {step} is not before stop_step {self.stop_step} "
                    "(STOP does not move, so it cannot collide; actions after it are ignored)"
                )

    @property
    def num_actions(self) -> int:
        return len(self.positions) - 1


def trajectory_of(record: EpisodeRecord) -> EpisodeTrajectory:
    """The metrics' view of a record: visited positions, STOP, collisions, goal and reference path."""
    return EpisodeTrajectory(
        episode_id=record.episode_id,
        scene_id=record.scene_id,
        positions=record.positions(),
        goal=record.goal,
        reference_path=record.reference_path,
        stopped=record.stopped,
        stop_step=record.stop_step,
        collision_steps=tuple(record.collision_steps),
    )


def trajectory_from_actions(
    episode_id: str,
    scene_id: str,
    start: Pose,
    actions: Sequence[int],
    goal,
    reference_path,
    collision_steps: Iterable[int] = (),
) -> EpisodeTrajectory:
    """Replay `actions` from `start` through `sim.dynamics` and wrap the result.

    The first STOP (id 0) ends the trajectory; actions after it are dropped.
    """
    actions = [int(a) for a in actions]
    stop_step = actions.index(C.ACTION_STOP) if C.ACTION_STOP in actions else None
    if stop_step is not None:
        actions = actions[: stop_step + 1]
    poses = rollout_array(start, actions)  # (T + 1, 4)
    return EpisodeTrajectory(
        episode_id=episode_id,
        scene_id=scene_id,
        positions=poses,
        goal=goal,
        reference_path=reference_path,
        stop_step=stop_step,
        collision_steps=tuple(collision_steps),
    )


def _distances(points: np.ndarray, target: np.ndarray, dims: int) -> np.ndarray:
    """(N, 3), (3,) -> (N,) Euclidean distances over the first `dims` axes."""
    return np.linalg.norm(points[:, :dims] - target[:dims], axis=1)


def _dedupe_consecutive(points: np.ndarray) -> np.ndarray:
    """Drop points equal to their predecessor (turns and STOP repeat positions). (N, D) -> (N', D)."""
    if len(points) < 2:
        return points
    keep = np.concatenate(([True], np.any(np.diff(points, axis=0) != 0, axis=1)))
    return points[keep]


def dtw_distance(query: np.ndarray, reference: np.ndarray) -> float:
    """Exact dynamic time warping distance with Euclidean point costs: (N, D), (M, D) -> float.

    Row by row: a cell's best diagonal/vertical predecessor is vectorised, and the horizontal chain
    D[i, j] = min(a[j], D[i, j - 1] + c[i, j]) is solved in closed form as
    S[j] + min_{k <= j} (a[k] - S[k]) with S the running sum of the row's costs. O(N M).
    """
    query = np.asarray(query, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if len(query) == 0 or len(reference) == 0:
        raise ValueError("dtw_distance needs two non-empty paths")
    cost = np.linalg.norm(query[:, None, :] - reference[None, :, :], axis=-1)  # (N, M)
    prev = None
    for row_cost in cost:  # (M,)
        if prev is None:
            best_pred = np.full_like(row_cost, np.inf)
            best_pred[0] = 0.0
        else:
            diagonal = np.concatenate(([np.inf], prev[:-1]))
            best_pred = np.minimum(prev, diagonal)
        entry = row_cost + best_pred  # (M,) cost when entering each cell from the row above
        running = np.cumsum(row_cost)
        prev = running + np.minimum.accumulate(entry - running)
    return float(prev[-1])


def ndtw(query: np.ndarray, reference: np.ndarray, threshold: float) -> float:
    """Normalised DTW, exp(-DTW / (|R| * d_th)), after dropping consecutive duplicate points."""
    query = _dedupe_consecutive(np.asarray(query, dtype=np.float64))
    reference = _dedupe_consecutive(np.asarray(reference, dtype=np.float64))
    return math.exp(-dtw_distance(query, reference) / (len(reference) * threshold))


def _evaluated_part(
    traj: EpisodeTrajectory, profile: MetricProfile
) -> tuple[np.ndarray, bool, list[int], bool]:
    """Cut the trajectory where the profile stops looking at it.

    Returns the evaluated positions (n + 1, 3) (or up to the collision), whether STOP was executed,
    the collision steps inside the evaluated actions, and whether a collision ended the episode.
    """
    num = traj.num_actions
    stop_step = traj.stop_step
    if stop_step is not None:
        num = min(num, stop_step + 1)
    if num > profile.max_steps:
        num = profile.max_steps
        if stop_step is not None and stop_step >= profile.max_steps:
            stop_step = None  # the STOP came after the step budget
    collisions = [s for s in traj.collision_steps if s < num]
    if profile.collision_policy == "end_fail" and collisions:
        # The colliding move is not executed: the episode ends where it was before that move.
        return traj.positions[: collisions[0] + 1], False, collisions[:1], True
    return traj.positions[: num + 1], stop_step is not None, collisions, False


def episode_metrics(traj: EpisodeTrajectory, profile: MetricProfile | str) -> dict:
    """Score one trajectory under one profile.

    Returns:
        A JSON-friendly dict: episode_id, scene_id, profile, ne (m), success, oracle_success, spl,
        ndtw, sdtw, path_length (m), steps (actions evaluated, STOP included), stopped, collided,
        num_collisions, ended_by_collision, outcome (`episode_outcome`) and its flags early_stop,
        stopped_far, stopped_after_passing, step_limit.
    """
    profile = get_profile(profile)
    positions, stopped, collisions, ended_by_collision = _evaluated_part(traj, profile)
    dims = profile.distance_dims
    distances = _distances(positions, traj.goal, dims)  # (n + 1,)
    ne = float(distances[-1])
    success = profile.within(ne) and (stopped or not profile.stop_required) and not ended_by_collision
    oracle_pool = distances if profile.osr_includes_start else distances[1:]
    oracle_success = bool(any(profile.within(float(d)) for d in oracle_pool))

    executed = path_length(positions)
    if profile.spl_reference == "straight_line":
        shortest = float(np.linalg.norm(traj.goal - traj.positions[0]))
    else:
        shortest = path_length(traj.reference_path)
    travelled = executed + profile.spl_path_epsilon
    denominator = max(travelled, shortest) if profile.spl_clamp else travelled
    if not success:
        spl = 0.0
    elif denominator > 0:
        spl = shortest / denominator
    else:
        spl = 1.0  # nothing to travel and nothing travelled: perfectly efficient by convention

    ndtw_value = ndtw(positions[:, :dims], traj.reference_path[:, :dims], profile.success_radius)
    stop_step = traj.stop_step if stopped else None
    outcome = episode_outcome(success, stopped, oracle_success, ended_by_collision, stop_step)
    return {
        "episode_id": traj.episode_id,
        "scene_id": traj.scene_id,
        "profile": profile.name,
        "ne": ne,
        "success": bool(success),
        "oracle_success": oracle_success,
        "spl": float(spl),
        "ndtw": ndtw_value,
        "sdtw": ndtw_value if success else 0.0,
        "path_length": float(executed),
        "steps": len(positions) - 1 + (1 if ended_by_collision else 0),
        "stopped": bool(stopped),
        "collided": bool(collisions),
        "num_collisions": len(collisions),
        "ended_by_collision": ended_by_collision,
        "outcome": outcome,
        "early_stop": outcome == "early_stop",
        "stopped_far": outcome == "stopped_far",
        "stopped_after_passing": outcome == "stopped_after_passing",
        "step_limit": outcome == "step_limit",
    }


def episode_outcome(
    success: bool,
    stopped: bool,
    oracle_success: bool,
    ended_by_collision: bool,
    stop_step: int | None = None,
) -> str:
    """Where a failed episode went wrong, one of `OUTCOMES`.

    "early_stop": a STOP among the first `EARLY_STOP_STEPS` actions (`stop_step` < 3: the agent gave up
    before flying; None: unknown, never early); "stopped_far": a STOP that never came within the success radius (the agent went somewhere else);
    "stopped_after_passing": a STOP outside the radius after the path was within it (it flew past or
    stopped short on the way back); "collision_end": a collision ended it (`end_fail` profiles);
    "step_limit": it never stopped (the step budget ran out, or a profile that needs no STOP).
    """
    if success:
        return "success"
    if ended_by_collision:
        return "collision_end"
    if stopped:
        if stop_step is not None and stop_step < EARLY_STOP_STEPS:
            return "early_stop"
        return "stopped_after_passing" if oracle_success else "stopped_far"
    return "step_limit"


def _summarise(rows: Sequence[dict]) -> dict:
    """Means of the per-episode metrics; rates and SPL / nDTW in percent (keys say the unit); the counts of
    successes and oracle successes; 95 % intervals of SR / OSR (Wilson) and SPL / NE (bootstrap), in the
    unit of their mean, as [low, high]."""
    summary: dict = {"episodes": len(rows)}
    for key, (name, scale) in _MEAN_KEYS.items():
        summary[name] = scale * float(np.mean([float(row[key]) for row in rows]))
    summary["successes"] = sum(bool(row["success"]) for row in rows)
    summary["oracle_successes"] = sum(bool(row["oracle_success"]) for row in rows)
    for interval_key, flag in _RATE_INTERVALS.values():
        low, high = wilson_interval(sum(bool(row[flag]) for row in rows), len(rows))
        summary[interval_key] = [100.0 * low, 100.0 * high]
    for interval_key, value_key, scale in _MEAN_INTERVALS.values():
        low, high = bootstrap_mean_interval([float(row[value_key]) for row in rows])
        summary[interval_key] = [scale * low, scale * high]
    return summary


def aggregate(per_episode: Sequence[dict], by: str | None = "scene") -> dict:
    """Average `episode_metrics` rows overall and per group.

    Args:
        per_episode: rows from `episode_metrics`, all of one profile.
        by: "scene" groups by `scene_id`; any other key of the rows groups by that key; None skips.

    Returns:
        {"profile", "overall": {...}, "per_<by>": {group: {...}}, "<by>_mean": {...}} where each
        summary holds `episodes`, `ne_m`, `sr_pct`, `osr_pct`, `spl_pct`, `ndtw_pct`, `sdtw_pct`,
        `path_length_m`, `steps`, `stop_rate_pct`, `collision_rate_pct`, `collisions_per_episode`,
        the outcome rates `early_stop_pct`, `stopped_far_pct`, `stopped_after_passing_pct`,
        `collision_end_pct`, `step_limit_pct` (with `sr_pct` they sum to 100), the counts `successes`
        and `oracle_successes`, and the 95 % intervals `sr_ci95`, `osr_ci95`, `spl_ci95`, `ne_ci95`;
        `<by>_mean` is the unweighted mean over groups (how the OpenFly README averages scenes), without
        counts or intervals.
    """
    rows = list(per_episode)
    if not rows:
        raise ValueError("aggregate() got no episodes")
    profiles = sorted({row["profile"] for row in rows})
    if len(profiles) != 1:
        raise ValueError(f"aggregate() got rows of several profiles {profiles}; aggregate each profile apart")
    result: dict = {"profile": profiles[0], "overall": _summarise(rows)}
    if by is None:
        return result
    key = "scene_id" if by == "scene" else by
    groups: dict[str, list[dict]] = {}
    for index, row in enumerate(rows):
        if key not in row:
            raise KeyError(
                f"aggregate(by={by!r}): row {index} ({row.get('episode_id')}) has no '{key}' field"
            )
        groups.setdefault(str(row[key]), []).append(row)
    per_group = {name: _summarise(group) for name, group in sorted(groups.items())}
    result[f"per_{by}"] = per_group
    group_mean = {"groups": len(per_group)}
    for name, _ in _MEAN_KEYS.values():
        group_mean[name] = float(np.mean([summary[name] for summary in per_group.values()]))
    result[f"{by}_mean"] = group_mean
    return result


def evaluate(
    trajectories: Iterable[EpisodeTrajectory], profile: MetricProfile | str, by: str | None = "scene"
) -> dict:
    """`aggregate` of `episode_metrics` over `trajectories` under one profile."""
    profile = get_profile(profile)
    return aggregate([episode_metrics(t, profile) for t in trajectories], by=by)


def evaluate_profiles(
    trajectories: Iterable[EpisodeTrajectory],
    profiles: Iterable[MetricProfile | str] = DEFAULT_PROFILE_NAMES,
    by: str | None = "scene",
) -> dict[str, dict]:
    """{profile name: `evaluate(...)`} for every profile (both named ones by default)."""
    trajectories = list(trajectories)
    resolved = [get_profile(p) for p in profiles]
    return {p.name: evaluate(trajectories, p, by=by) for p in resolved}
