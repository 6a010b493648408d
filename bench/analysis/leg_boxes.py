"""Which landmark the agent's box is on at each step of a chained route: the current leg's target, another leg's,
one the route does not name, or none (pure functions; bench/leg_boxes.py renders the flights again).

An agent trained on leg boxes (`render.box_target: leg`) must box the target of the leg it is on. Where its box sits
on an earlier or a later leg's landmark, it knows the landmarks but not where along the route it is (what the
memory has to carry); where it sits on no landmark, or on one the route does not name, its grounding misses the
landmark itself. The leg is tracked as the runner tracks it for `--true_box=leg` (rollout/legs.py `current_leg`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

from bench.analysis.stop_landmarks import NO_BOX, ON_NOTHING, Box, best_landmark
from bench.analysis.stop_landmarks import ON_OTHER_LANDMARK as ON_OTHER

ON_LEG = "the current leg's target"
ON_EARLIER = "an earlier leg's target"
ON_LATER = "a later leg's target"
CATEGORIES = (ON_LEG, ON_EARLIER, ON_LATER, ON_OTHER, ON_NOTHING, NO_BOX)


def leg_box_category(predicted: Box | None, boxes: dict[str, Box], route: Sequence[str], leg: int) -> str:
    """Which landmark the agent's box is on (one of `CATEGORIES`).

    Args:
        predicted: the agent's box at the step, None when it saw none.
        boxes: landmark id -> its true box in the frame at the step's pose (the visible ones).
        route: the route's target landmarks, one per leg, in order.
        leg: the index in `route` of the leg the drone is on.
    """
    if predicted is None:
        return NO_BOX
    best = best_landmark(predicted, boxes)
    if best is None:
        return ON_NOTHING
    if best not in route:
        return ON_OTHER
    index = list(route).index(best)
    return ON_LEG if index == leg else ON_EARLIER if index < leg else ON_LATER


class LegBoxCounts:
    """Steps per category, apart for the steps with the current leg's target in view and out of it."""

    def __init__(self) -> None:
        self.counts: Counter = Counter()

    def add(self, category: str, target_in_view: bool) -> None:
        if category not in CATEGORIES:
            raise ValueError(f"unknown category {category!r}")
        self.counts[category, bool(target_in_view)] += 1

    def table(self) -> list[tuple[str, int, int]]:
        """(category, steps with the current leg's target in view, steps with it out of view) per category."""
        return [(c, self.counts[c, True], self.counts[c, False]) for c in CATEGORIES]

    def markdown(self) -> str:
        """The table with each column's share of its steps, totals last."""
        rows = self.table()
        in_view, out_of_view = sum(r[1] for r in rows), sum(r[2] for r in rows)

        def cell(count: int, total: int) -> str:
            return f"{count} ({100 * count / total:.1f} %)" if total else "0"

        lines = [
            "| the agent's box is on | steps, the current leg's target in view | steps, out of view |",
            "|---|---:|---:|",
        ]
        lines += [f"| {c} | {cell(a, in_view)} | {cell(b, out_of_view)} |" for c, a, b in rows]
        lines.append(f"| all | {in_view} | {out_of_view} |")
        return "\n".join(lines) + "\n"
