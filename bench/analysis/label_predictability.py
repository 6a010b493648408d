"""How predictable are a dataset's expert actions from privileged per-step features?

A diagnostic for generated data, not part of training: small MLP probes fit the expert action of every
step from ground-truth quantities an agent can only infer (the target landmark's box in the current frame,
the goal's distance and bearing) and report held-out accuracy next to the majority-class rate. The gap
between the probes and the majority rate bounds what perfect grounding (box probe) or perfect localisation
(goal probe) could buy an imitation learner on this data; `bench/label_predictability.py` prints it.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from openfly_agent.data.schema import Episode

logger = logging.getLogger(__name__)

BOX_FEATURES = ("visible", "cx", "cy", "w", "h", "area")
GOAL_FEATURES = ("goal_distance", "goal_bearing", "altitude", "goal_altitude")
LEG_FEATURES = ("leg_goal_distance", "leg_goal_bearing")
FEATURE_NAMES = BOX_FEATURES + GOAL_FEATURES + ("step", "previous_action") + LEG_FEATURES
DISTANCE_SCALE_M = 50.0  # features are divided by this to keep them near unit scale


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Radians wrapped to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def leg_goal_per_step(episode: Episode) -> np.ndarray:
    """(T, 3) the goal of the leg each step belongs to: a leg ends at the step nearest its goal after the previous
    leg's end (the A* path reaches each leg's goal within its tolerance there), and that step is the next leg's
    first decision, as the toolchain's leg boxes count it. Without `leg_goals`: the last position at every step."""
    positions = np.asarray(episode.positions, dtype=np.float64)[: len(episode.actions)]  # (T, 3)
    if episode.leg_goals is None or len(episode.leg_goals) < 2:
        return np.repeat(positions[-1:], len(positions), axis=0)
    goals = np.asarray(episode.leg_goals, dtype=np.float64)  # (K, 3)
    ends, start = [], 0
    for goal in goals[:-1]:
        start += int(np.argmin(np.linalg.norm(positions[start:] - goal, axis=1)))
        ends.append(start)
    legs = np.searchsorted(np.asarray(ends), np.arange(len(positions)), side="right")  # (T,) 0 .. K-1
    return goals[legs]


def _distance_and_bearing(positions: np.ndarray, yaws: np.ndarray, goals: np.ndarray):
    """(T,) horizontal distance to each step's goal over DISTANCE_SCALE_M, and its bearing off the heading."""
    delta = goals[:, :2] - positions[:, :2]  # (T, 2)
    bearing = wrap_angle(np.arctan2(delta[:, 1], delta[:, 0]) - yaws)
    return np.linalg.norm(delta, axis=1) / DISTANCE_SCALE_M, bearing


def step_features(episode: Episode) -> np.ndarray:
    """(T, len(FEATURE_NAMES)) float32 features of every step of `episode`.

    The goal is the episode's last position (where the expert stops). `goal_bearing` is the goal's direction
    relative to the current heading, counter-clockwise positive (a goal on the left is > 0), in radians.
    Box features are zero where the target landmark is not visible (or the episode has no boxes).
    `previous_action` is (a[t-1] + 1) / 10, 0 at the first step (an expert quantity the model never sees).
    `leg_goal_*`: the same for the goal of the step's leg on a chained route (`leg_goal_per_step`; the goal
    itself on a route of one leg or without `leg_goals`).
    """
    n = len(episode.actions)
    positions = np.asarray(episode.positions, dtype=np.float64)[:n]  # (T, 3)
    yaws = np.asarray(episode.yaws, dtype=np.float64)[:n]  # (T,)
    goal = positions[-1]
    distance, bearing = _distance_and_bearing(positions, yaws, np.repeat(goal[None], n, axis=0))
    leg_distance, leg_bearing = _distance_and_bearing(positions, yaws, leg_goal_per_step(episode))
    if episode.boxes is not None and episode.box_visible is not None:
        visible = np.asarray(episode.box_visible, dtype=np.float64)[:n]
        boxes = np.asarray(episode.boxes, dtype=np.float64)[:n] * visible[:, None]  # (T, 4)
    else:
        visible, boxes = np.zeros(n), np.zeros((n, 4))
    columns = [
        visible,
        *boxes.T,
        boxes[:, 2] * boxes[:, 3],
        distance,
        bearing,
        positions[:, 2] / DISTANCE_SCALE_M,
        np.full(n, goal[2] / DISTANCE_SCALE_M),
        np.arange(n) / 20.0,
        np.concatenate([[0.0], (np.asarray(episode.actions[:-1], dtype=np.float64) + 1.0) / 10.0]),
        leg_distance,
        leg_bearing,
    ]
    return np.stack(columns, axis=1).astype(np.float32)


def dataset_features(episodes: Sequence[Episode]) -> tuple[np.ndarray, np.ndarray]:
    """Features (N, F) and expert actions (N,) of every step of `episodes`."""
    if not episodes:
        raise ValueError("no episodes")
    features = np.concatenate([step_features(e) for e in episodes])
    actions = np.concatenate([np.asarray(e.actions, dtype=np.int64) for e in episodes])
    return features, actions


def majority_rate(train_actions: np.ndarray, test_actions: np.ndarray) -> tuple[int, float]:
    """The train split's most frequent action and its share of the test actions."""
    majority = collections.Counter(train_actions.tolist()).most_common(1)[0][0]
    return int(majority), float(np.mean(test_actions == majority))


@dataclass
class ProbeResult:
    """Held-out and train accuracy of one probe."""

    name: str
    features: tuple[str, ...]
    test_accuracy: float
    train_accuracy: float


def fit_probe(
    train_x: np.ndarray,
    train_y: np.ndarray,
    test_x: np.ndarray,
    test_y: np.ndarray,
    epochs: int = 100,
    hidden: int = 128,
    batch_size: int = 512,
    seed: int = 0,
    num_classes: int = 10,
) -> tuple[float, float]:
    """Train a 2-hidden-layer MLP with cross-entropy; return (test accuracy, train accuracy)."""
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    x, y = torch.as_tensor(train_x, dtype=torch.float32), torch.as_tensor(train_y, dtype=torch.long)
    model = nn.Sequential(
        nn.Linear(x.shape[1], hidden),
        nn.ReLU(),
        nn.Linear(hidden, hidden),
        nn.ReLU(),
        nn.Linear(hidden, num_classes),
    )
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    for _ in range(epochs):
        order = torch.randperm(len(x), generator=generator)
        for start in range(0, len(x), batch_size):
            idx = order[start : start + batch_size]
            loss = nn.functional.cross_entropy(model(x[idx]), y[idx])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    with torch.no_grad():
        test_pred = model(torch.as_tensor(test_x, dtype=torch.float32)).argmax(-1).numpy()
        train_pred = model(x).argmax(-1).numpy()
    return float(np.mean(test_pred == test_y)), float(np.mean(train_pred == train_y))


PROBES: dict[str, tuple[str, ...]] = {
    "target box (perfect grounding)": BOX_FEATURES,
    "target box + step index": BOX_FEATURES + ("step",),
    "goal distance + bearing (perfect localisation)": ("goal_distance", "goal_bearing"),
    "goal distance + bearing + altitudes": GOAL_FEATURES,
    "previous expert action": ("previous_action",),
    "current leg's goal distance + bearing (perfect localisation on the route)": LEG_FEATURES,
}


def run_probes(
    train: Sequence[Episode], test: Sequence[Episode], epochs: int = 100, seed: int = 0
) -> tuple[tuple[int, float], list[ProbeResult]]:
    """The majority rate and every probe of `PROBES`, fitted on `train`, scored on `test`."""
    train_x, train_y = dataset_features(train)
    test_x, test_y = dataset_features(test)
    results = []
    for name, features in PROBES.items():
        cols = [FEATURE_NAMES.index(f) for f in features]
        test_acc, train_acc = fit_probe(train_x[:, cols], train_y, test_x[:, cols], test_y, epochs, seed=seed)
        logger.info("probe %s: test %.3f train %.3f", name, test_acc, train_acc)
        results.append(ProbeResult(name, features, test_acc, train_acc))
    return majority_rate(train_y, test_y), results
