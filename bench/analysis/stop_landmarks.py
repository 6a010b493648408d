"""Where an evaluated agent stops, and on what: each STOP of its flights classified against the simulator's boxes.

A STOP far from the goal can be a hasty STOP near the target or a flight to another landmark. The flight's record
holds the box the agent predicted at its STOP; the simulator, rendered again at the STOP's pose, holds every
landmark's true box there. This module compares the two (pure functions; bench/stop_landmarks.py renders).

Categories of one STOP (`stop_target`): the landmark whose true box best overlaps the agent's box, if any overlaps
by `MIN_IOU`: the route's target, another landmark the route names, a landmark the route does not name, or none.
A STOP on another landmark than the target also says which of the target's `ATTRIBUTES` that landmark shares,
next to how many of the landmarks in view share each (`shared_in_view`: what a pick at random would give).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

MIN_IOU = 0.3  # the agent's box is "on" a landmark when their IoU reaches this
ON_TARGET = "the target"
ON_ROUTE_LANDMARK = "another landmark the route names"
ON_OTHER_LANDMARK = "a landmark the route does not name"
ON_NOTHING = f"no landmark (IoU < {MIN_IOU})"
NO_BOX = "the agent saw no box"
CATEGORIES = (ON_TARGET, ON_ROUTE_LANDMARK, ON_OTHER_LANDMARK, ON_NOTHING, NO_BOX)
ATTRIBUTES = ("type", "color", "size", "shape", "feature")  # what an instruction describes a landmark by

Box = Sequence[float]  # (cx, cy, w, h), fractions of the frame


def box_iou(a: Box, b: Box) -> float:
    """IoU of two (cx, cy, w, h) boxes."""
    ax0, ay0, ax1, ay1 = a[0] - a[2] / 2, a[1] - a[3] / 2, a[0] + a[2] / 2, a[1] + a[3] / 2
    bx0, by0, bx1, by1 = b[0] - b[2] / 2, b[1] - b[3] / 2, b[0] + b[2] / 2, b[1] + b[3] / 2
    inter = max(0.0, min(ax1, bx1) - max(ax0, bx0)) * max(0.0, min(ay1, by1) - max(ay0, by0))
    union = a[2] * a[3] + b[2] * b[3] - inter
    return inter / union if union > 0 else 0.0


def best_landmark(predicted: Box | None, boxes: dict[str, Box]) -> str | None:
    """The landmark whose true box overlaps the agent's box most, if by `MIN_IOU` at least (else None)."""
    if predicted is None:
        return None
    best_iou, best = max(
        ((box_iou(predicted, box), landmark) for landmark, box in boxes.items()), default=(0.0, "")
    )
    return best if best_iou >= MIN_IOU else None


def stop_target(predicted: Box | None, boxes: dict[str, Box], target: str, route: Sequence[str]) -> str:
    """Which landmark the agent's box is on at a STOP (one of `CATEGORIES`).

    Args:
        predicted: the agent's box at the STOP, None when it saw none.
        boxes: landmark id -> its true box in the frame at the STOP's pose (the visible ones).
        target: the route's target landmark (its last).
        route: every landmark the route names.
    """
    if predicted is None:
        return NO_BOX
    best = best_landmark(predicted, boxes)
    if best is None:
        return ON_NOTHING
    if best == target:
        return ON_TARGET
    return ON_ROUTE_LANDMARK if best in route else ON_OTHER_LANDMARK


def shared_attributes(a: object, b: object) -> list[str]:
    """The `ATTRIBUTES` two landmarks (sim/scene.py `Landmark`) have in common."""
    return [name for name in ATTRIBUTES if getattr(a, name) == getattr(b, name)]


@dataclass
class StopRow:
    """One flight that ended with a STOP."""

    episode_id: str
    success: bool  # the STOP is within the success radius
    distance_m: float  # from the goal at the STOP
    target_in_view: bool  # the target has a true box at the STOP's pose
    on: str  # `stop_target`
    # on another landmark: the target's `ATTRIBUTES` it shares (None: on the target, on none, or no box)
    shared: list[str] | None = None
    # ... and per attribute, the share of the other landmarks in view that have the target's (the chance level)
    shared_in_view: dict[str, float] | None = None


def stop_table(rows: Iterable[StopRow]) -> list[tuple[str, int, int, int]]:
    """(category, STOPs at the goal, STOPs far from it, of those far ones: the target in view) per category."""
    counts: Counter = Counter()
    for row in rows:
        counts[row.on, row.success] += 1
        if not row.success and row.target_in_view:
            counts[row.on, "far in view"] += 1
    return [
        (category, counts[category, True], counts[category, False], counts[category, "far in view"])
        for category in CATEGORIES
    ]


def table_markdown(rows: list[StopRow]) -> str:
    """The classified STOPs as a markdown table, totals last."""
    lines = [
        "| the agent's box at its STOP is on | STOPs at the goal | STOPs far from it | ... target in view |",
        "|---|---:|---:|---:|",
    ]
    for category, near, far, in_view in stop_table(rows):
        lines.append(f"| {category} | {near} | {far} | {in_view} |")
    near = sum(r.success for r in rows)
    in_view = sum(not r.success and r.target_in_view for r in rows)
    lines.append(f"| all | {near} | {len(rows) - near} | {in_view} |")
    return "\n".join(lines) + "\n"


def shared_in_view(target: object, others: Sequence[object]) -> dict[str, float]:
    """Per attribute, the share of `others` (the non-target landmarks in view) that have the target's value."""
    if not others:
        return dict.fromkeys(ATTRIBUTES, 0.0)
    return {
        name: sum(getattr(o, name) == getattr(target, name) for o in others) / len(others)
        for name in ATTRIBUTES
    }


def shared_markdown(rows: list[StopRow]) -> str:
    """Of the far STOPs on another landmark than the target: how many share each attribute with the target, next
    to the share expected if the agent had picked one of the other landmarks in view at random."""
    wrong = [r for r in rows if not r.success and r.shared is not None]
    if not wrong:
        return ""
    n = len(wrong)

    def pct(count: float) -> str:
        return f"{100 * count / n:.0f} %"

    picked = [pct(sum(name in r.shared for r in wrong)) for name in ATTRIBUTES]
    chance = [pct(sum((r.shared_in_view or {}).get(name, 0.0) for r in wrong)) for name in ATTRIBUTES]
    return (
        f"Far STOPs on another landmark than the target ({n}): share of them on a landmark with the target's ...\n\n"
        f"| | {' | '.join(ATTRIBUTES)} |\n|---|{'---:|' * len(ATTRIBUTES)}\n"
        f"| the landmark stopped at | {' | '.join(picked)} |\n"
        f"| a landmark in view at random (chance) | {' | '.join(chance)} |\n"
    )
