"""Sub-trajectories for instruction generation: split at action transitions, the landmark seen at each end.

As the paper (and the official `ins_gen`): the trajectory is cut wherever the action type changes; each
piece is described by its action and by the landmark seen in the frame where it ends; the last piece ends at
the target landmark.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from openfly_agent import constants as C
from openfly_agent.sim.scene import Landmark

FORWARD, LEFT, RIGHT, UP, DOWN = "forward", "left", "right", "up", "down"
TAKEOFF, LANDING, STOP = "takeoff", "landing", "stop"
NAMING_KINDS = (FORWARD, LEFT, RIGHT)  # the sub-trajectories whose clause names their landmark
_KIND = {
    C.ACTION_FORWARD: FORWARD,
    C.ACTION_FORWARD_6: FORWARD,
    C.ACTION_FORWARD_9: FORWARD,
    C.ACTION_TURN_LEFT: LEFT,
    C.ACTION_TURN_RIGHT: RIGHT,
    C.ACTION_ASCEND: UP,
    C.ACTION_DESCEND: DOWN,
    C.ACTION_MOVE_LEFT: "move_left",
    C.ACTION_MOVE_RIGHT: "move_right",
    C.ACTION_TAKEOFF: TAKEOFF,
    C.ACTION_LANDING: LANDING,
    C.ACTION_STOP: STOP,
}
_FORWARD_METRES = {C.ACTION_FORWARD: 3.0, C.ACTION_FORWARD_6: 6.0, C.ACTION_FORWARD_9: 9.0}


@dataclass
class Segment:
    """A run of one action kind: frames [start, end) carry its actions; `end` is the frame it arrives at."""

    kind: str
    start: int
    end: int
    primitives: int  # 30 deg turns, or 3 m steps (forward / vertical / lateral)
    landmark_id: str | None = None  # the landmark seen at `end` (or the leg target)
    forced: bool = False  # the landmark is a route target (not just what is visible)
    passed_id: str | None = None  # the route target just reached: "after passing <it>, ..." (see mark_passed)

    @property
    def metres(self) -> float:
        return C.STEP_METERS * self.primitives

    @property
    def degrees(self) -> float:
        return C.TURN_DEGREES * self.primitives


@dataclass
class InstructionRequest:
    """Everything an instruction backend needs for one trajectory."""

    actions: np.ndarray  # (T,) ids -2..9
    frame_boxes: list[dict[str, np.ndarray]]  # per frame: visible landmark id -> (cx, cy, w, h)
    landmarks: dict[str, Landmark]  # id -> landmark (attributes to name)
    target_ids: list[str]  # route targets in order; the last is the final target
    leg_end_frames: list[int]  # frame where each leg ends (the last = the STOP frame)
    seed: int = 0
    frames: list[np.ndarray] | None = None  # (H, W, 3) uint8, used by the VLM backend
    min_box_area: float = 0.002
    merge_short_m: float = 9.0  # see merge_short_segments; 0 = one clause per action transition
    name_every_target: bool = False  # see assign_landmarks
    name_passed_landmark: bool = False  # see mark_passed
    extra: dict = field(default_factory=dict)


def split_at_transitions(actions: np.ndarray) -> list[Segment]:
    """Runs of equal action kind (forward 3/6/9 m are one kind); the STOP frame ends the navigation.

    >>> [(s.kind, s.start, s.end, s.primitives) for s in split_at_transitions([3, 9, 8, 2, 0])]
    [('right', 0, 1, 1), ('forward', 1, 3, 5), ('left', 3, 4, 1)]
    """
    actions = [int(a) for a in actions]
    segments: list[Segment] = []
    for t, action in enumerate(actions):
        if action not in _KIND:
            raise ValueError(f"unknown action id {action} at frame {t}")
        kind = _KIND[action]
        if kind == STOP:
            continue
        units = int(_FORWARD_METRES.get(action, C.STEP_METERS) / C.STEP_METERS)
        if segments and segments[-1].kind == kind and segments[-1].end == t:
            segments[-1].end, segments[-1].primitives = t + 1, segments[-1].primitives + units
        else:
            segments.append(Segment(kind, t, t + 1, units))
    return segments


# Opposite action pairs that cancel: (positive kind, negative kind).
_AXES = ((LEFT, RIGHT), (UP, DOWN))


def _axis(seg: Segment) -> tuple[str, str] | None:
    return next((axis for axis in _AXES if seg.kind in axis), None)


def _signed(seg: Segment) -> int:
    """Turns (left +) or climbs (up +) of a turn / vertical segment."""
    return seg.primitives if seg.kind == _axis(seg)[0] else -seg.primitives


def _net(axis: tuple[str, str], start: int, end: int, net: int) -> list[Segment]:
    return [Segment(axis[0] if net > 0 else axis[1], start, end, abs(net))] if net else []


def _fuse_neighbours(segments: list[Segment]) -> list[Segment]:
    """Join consecutive forward runs, and consecutive turns (climbs) into their net turn (climb)."""
    out: list[Segment] = []
    for seg in segments:
        last = out[-1] if out else None
        if last is not None and last.kind == seg.kind == FORWARD:
            out[-1] = Segment(FORWARD, last.start, seg.end, last.primitives + seg.primitives)
        elif last is not None and _axis(last) is not None and _axis(last) == _axis(seg):
            out[-1:] = _net(_axis(seg), last.start, seg.end, _signed(last) + _signed(seg))
        else:
            out.append(seg)
    return out


def merge_short_segments(segments: list[Segment], min_forward_m: float) -> list[Segment]:
    """Fold jogs into the legs around them: a forward run shorter than `min_forward_m` between two turns
    (or two climbs / descents) is dropped and they become their net turn (climb), nothing when they
    cancel, so each remaining sub-trajectory is a maneuver worth a clause. `min_forward_m` = 0 keeps every
    transition (as the paper splits).

    >>> segs = split_at_transitions([9, 9, 2, 1, 3, 9, 9, 3, 8, 3, 9, 4, 1, 4, 0])
    >>> [(s.kind, s.primitives) for s in merge_short_segments(segs, 9.0)]
    [('forward', 12), ('right', 2), ('forward', 3), ('up', 2)]
    """
    out = _fuse_neighbours(list(segments))
    i = 1
    while i < len(out) - 1:
        prev, mid, nxt = out[i - 1], out[i], out[i + 1]
        axis = _axis(prev)
        if mid.kind == FORWARD and mid.metres < min_forward_m and axis is not None and axis == _axis(nxt):
            out[i - 1 : i + 2] = _net(axis, prev.start, nxt.end, _signed(prev) + _signed(nxt))
            out, i = _fuse_neighbours(out), 1
        else:
            i += 1
    return out


def box_area(box) -> float:
    return float(box[2] * box[3])


def seen_landmark(boxes: dict[str, np.ndarray], min_area: float, exclude: set | None = None) -> str | None:
    """The most prominent visible landmark of a frame: the largest box covering at least `min_area`."""
    best, best_area = None, min_area
    for landmark_id, box in boxes.items():
        area = box_area(box)
        if area >= best_area and not (exclude and landmark_id in exclude):
            best, best_area = landmark_id, area
    return best


def image_side(box) -> str:
    """'left' / 'center' / 'right' third of the image for a box centre (the official 'dir' of the target)."""
    if box is None:
        return "center"
    cx = float(box[0])
    return "left" if cx < 1.0 / 3.0 else ("right" if cx > 2.0 / 3.0 else "center")


def assign_landmarks(request: InstructionRequest, segments: list[Segment]) -> list[Segment]:
    """Set each segment's landmark: leg targets where legs end, else the most prominent visible one.

    A leg target goes to the segment in which its leg ends. With `request.name_every_target` it goes to the
    first segment from there on that names a landmark (a forward run or a turn, not a climb) and holds no
    earlier target, so every target of a chained route is named, in order (the last one at least by the
    closing stop clause). With `request.name_passed_landmark` the clause after each leg end also names the
    target just reached (`mark_passed`).
    """
    nav = [s for s in segments if s.kind not in (TAKEOFF, LANDING)]
    last_frame = len(request.frame_boxes) - 1
    for seg in nav:
        frame = min(seg.end, last_frame)
        seg.landmark_id = seen_landmark(request.frame_boxes[frame], request.min_box_area)
    for target, end_frame in zip(request.target_ids, request.leg_end_frames):
        owners = [s for s in nav if s.start < end_frame <= s.end] or [s for s in nav if s.end <= end_frame][
            -1:
        ]
        if owners and request.name_every_target:
            first = next(i for i, s in enumerate(nav) if s is owners[0])
            owners = [s for s in nav[first:] if s.kind in NAMING_KINDS and not s.forced]
        if owners:
            owners[0].landmark_id, owners[0].forced = target, True
    if request.name_passed_landmark:
        mark_passed(request, nav)
    return segments


def mark_passed(request: InstructionRequest, nav: list[Segment]) -> None:
    """Give the clause after each leg end the target just reached as its `passed_id` ("after passing the red
    tower, turn left toward the blue building"): the first forward run or turn that starts at or after the
    leg's end frame and before the next leg's, and does not itself name that target. The final target is
    never passed (the route stops there)."""
    ends = request.leg_end_frames
    for k, target in enumerate(request.target_ids[:-1]):
        clause = next(
            (
                s
                for s in nav
                if ends[k] <= s.start < ends[k + 1] and s.kind in NAMING_KINDS and s.landmark_id != target
            ),
            None,
        )
        if clause is not None:
            clause.passed_id = target


def deciding_landmark(seg: Segment) -> str | None:
    """The landmark whose position decides a clause's action: the target just passed in an "after passing X"
    clause (when the action is due), else the landmark a forward run or turn names (where it leads); None for
    a clause that names none (climbs and descents)."""
    if seg.kind not in NAMING_KINDS:
        return None
    return seg.passed_id or seg.landmark_id
