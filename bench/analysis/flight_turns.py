"""How an evaluated agent turns: turns and reversals per 100 actions, how often a turn is undone at once, and
whether the agent turns after its grounding head switches landmarks.

A reversal is a turn right after a turn the other way (left then right, or right then left): the expert never
flies one. A head switch is a step after an action that is not a turn whose predicted box overlaps the previous
step's by less than `SWITCH_IOU` (both predicted visible): the view barely moved, so the head moved to another
landmark. The turn rate right after a switch, against after the other such steps, says whether the action
chases the head's box; the turn-back rate (reversals per turn followed by an action) says whether it undoes its
own turns.
"""

from __future__ import annotations

from dataclasses import dataclass

from bench.analysis.stop_landmarks import box_iou
from openfly_agent.constants import ACTION_TURN_LEFT, ACTION_TURN_RIGHT

# consecutive boxes overlapping less than this, after a step that is not a turn, are a switch
SWITCH_IOU = 0.2
TURNS = {ACTION_TURN_LEFT, ACTION_TURN_RIGHT}


@dataclass
class TurnCounts:
    """Counts over a policy's flights."""

    actions: int = 0
    turns: int = 0
    turns_followed: int = 0  # turns with another action after them
    reversals: int = 0
    straight_steps: int = 0  # steps after an action that is not a turn, both boxes visible
    switches: int = 0
    turns_after_switch: int = 0
    turns_after_straight: int = 0  # after the straight steps that are not switches

    def add_flight(self, actions: list[int], boxes: list[list[float] | None]) -> None:
        """One flight's actions and the box predicted at each of its steps (None: not visible)."""
        self.actions += len(actions)
        self.turns += sum(action in TURNS for action in actions)
        for step in range(1, len(actions)):
            previous, action = actions[step - 1], actions[step]
            if previous in TURNS:
                self.turns_followed += 1
                self.reversals += {previous, action} == TURNS
                continue
            if step >= len(boxes) or boxes[step - 1] is None or boxes[step] is None:
                continue
            self.straight_steps += 1
            if box_iou(boxes[step - 1], boxes[step]) < SWITCH_IOU:
                self.switches += 1
                self.turns_after_switch += action in TURNS
            else:
                self.turns_after_straight += action in TURNS

    def summary(self) -> dict:
        """Rates in percent (None where nothing was counted)."""

        def percent(part: int, whole: int) -> float | None:
            return round(100 * part / whole, 1) if whole else None

        return {
            "actions": self.actions,
            "turns_per_100": percent(self.turns, self.actions),
            "reversals_per_100": percent(self.reversals, self.actions),
            "turn_back_percent": percent(self.reversals, self.turns_followed),
            "head_switch_percent": percent(self.switches, self.straight_steps),
            "turn_after_switch_percent": percent(self.turns_after_switch, self.switches),
            "turn_after_no_switch_percent": percent(
                self.turns_after_straight, self.straight_steps - self.switches
            ),
        }
