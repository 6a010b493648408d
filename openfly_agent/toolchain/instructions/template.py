"""Template instructions (offline default): action phrases + landmark names, fused, with pronouns.

Each sub-trajectory becomes a clause ("turn left toward the red office building"; with `name_passed_landmark`
the clause after a leg's end starts "after passing <the target just reached>, "), the clauses are joined with
varied connectors, the last one ends with the stop at the target, and a landmark mentioned again right after
itself becomes "it". Synonyms are drawn from a generator seeded per trajectory, so the text is reproducible.
"""

from __future__ import annotations

import numpy as np

from openfly_agent.sim.scene import Landmark
from openfly_agent.toolchain.instructions.segments import (
    DOWN,
    FORWARD,
    LANDING,
    LEFT,
    NAMING_KINDS,
    RIGHT,
    TAKEOFF,
    UP,
    InstructionRequest,
    Segment,
    assign_landmarks,
    merge_short_segments,
    split_at_transitions,
)

_UNNAMED = {"", "none", "test", "unknown", "n/a"}
_SIZE_WORDS = {
    "high-rise": "tall",
    "skyscraper": "tall",
    "tall": "tall",
    "low-rise": "low",
    "low": "low",
    "small": "small",
    "large": "large",
    "huge": "huge",
}

PHRASES = {
    FORWARD: [
        "fly forward",
        "go straight",
        "proceed straight ahead",
        "move ahead",
        "head forward",
        "continue straight",
    ],
    LEFT: ["turn left", "make a left turn", "bear left", "swing left"],
    RIGHT: ["turn right", "make a right turn", "bear right", "swing right"],
    "slight_left": ["turn slightly left", "veer slightly left", "bear a little to the left"],
    "slight_right": ["turn slightly right", "veer slightly right", "bear a little to the right"],
    "around": ["turn around", "make a U-turn"],
    UP: ["climb", "ascend", "fly up", "gain altitude by"],
    DOWN: ["descend", "fly down", "drop", "lose altitude by"],
    TAKEOFF: ["Take off", "Lift off", "Rise from the ground"],
    LANDING: ["land", "touch down", "descend to the ground"],
    "move_left": ["shift to the left", "slide left"],
    "move_right": ["shift to the right", "slide right"],
}
TOWARD = ["toward", "towards", "in the direction of"]
FACING = ["to face", "toward", "so that you face"]
REACH = ["until you reach", "until you are next to", "up to"]
PASSED = ["after passing", "once you have passed", "having passed"]
STOP = ["stop in front of", "stop next to", "stop near", "halt beside", "come to a stop by"]
CONNECTORS = [", then ", ", and then ", ". Then ", ". After that, ", ". Next, ", ", after which "]


def is_named(value: str) -> bool:
    """Whether an attribute value is a real name (not empty, "none", "unknown", ...)."""
    return bool(value) and value.strip().lower() not in _UNNAMED


def size_word(landmark: Landmark) -> str | None:
    """'tall' / 'low' / ... for the landmark's size class, None when it has no size word (mid-rise)."""
    return _SIZE_WORDS.get(landmark.size.strip().lower()) if landmark.size else None


def feature_phrase(feature: str, rng: np.random.Generator) -> str:
    """'with a spire', 'that has an antenna', 'featuring a dome' (one draw of `rng`)."""
    plural = feature.endswith("s") and not feature.endswith("ss")
    article = "" if plural else ("an " if feature[0].lower() in "aeiou" else "a ")
    lead = ["with", "with", "that has", "featuring"][rng.integers(4)]
    return f"{lead} {article}{feature}"


def describe_landmark(landmark: Landmark, rng: np.random.Generator) -> str:
    """Noun phrase naming colour, type, feature (size sometimes): 'the tall red tower with a spire'."""
    words = []
    size = size_word(landmark)
    if size and rng.random() < 0.5:
        words.append(size)
    if is_named(landmark.color):
        words.append(landmark.color)
    words.append(landmark.type if is_named(landmark.type) else "building")
    text = "the " + " ".join(words)
    if is_named(landmark.feature):
        text += " " + feature_phrase(landmark.feature, rng)
    return text


def short_name(landmark: Landmark) -> str:
    """'the red tower': what a repeated (not immediately repeated) mention uses."""
    color = f"{landmark.color} " if is_named(landmark.color) else ""
    return f"the {color}{landmark.type if is_named(landmark.type) else 'building'}"


class _Mentions:
    """Names landmarks: full description first, 'it' right after itself, a short name later on."""

    def __init__(self, landmarks: dict[str, Landmark], rng: np.random.Generator):
        self.landmarks, self.rng, self.seen, self.last = landmarks, rng, set(), None

    def __call__(self, landmark_id: str) -> str:
        landmark = self.landmarks[landmark_id]
        if landmark_id == self.last:
            text = "it"
        elif landmark_id in self.seen:
            text = short_name(landmark)
        else:
            text = describe_landmark(landmark, self.rng)
        self.seen.add(landmark_id)
        self.last = landmark_id
        return text


def _pick(rng: np.random.Generator, options: list[str]) -> str:
    return options[int(rng.integers(len(options)))]


def _distance(metres: float) -> str:
    return f"about {int(5 * round(metres / 5))} meters" if metres >= 10 else f"{int(round(metres))} meters"


def action_phrase(seg: Segment, rng: np.random.Generator, mention_distance: bool) -> str:
    """A varied phrase for one sub-trajectory's action ('turn slightly left', 'climb 6 meters', ...)."""
    if seg.kind in (LEFT, RIGHT):
        if seg.primitives >= 6:
            return _pick(rng, PHRASES["around"])
        key = f"slight_{seg.kind}" if seg.primitives == 1 else seg.kind
        return _pick(rng, PHRASES[key])
    phrase = _pick(rng, PHRASES[seg.kind])
    if seg.kind in (UP, DOWN):
        return f"{phrase} {_distance(seg.metres)}"
    if seg.kind == FORWARD and mention_distance and seg.metres >= 15 and rng.random() < 0.5:
        return f"{phrase} {_distance(seg.metres)}"
    return phrase


def _clause(seg: Segment, name, rng: np.random.Generator, mention_distance: bool, is_last: bool) -> str:
    # "after passing the red tower, turn left ..." (drawn only then, so other instructions keep their draws)
    text = f"{_pick(rng, PASSED)} {name(seg.passed_id)}, " if seg.passed_id is not None else ""
    text += action_phrase(seg, rng, mention_distance)
    if seg.landmark_id is None or seg.kind not in NAMING_KINDS:
        return text
    if seg.kind in (LEFT, RIGHT):
        return f"{text} {_pick(rng, FACING)} {name(seg.landmark_id)}"
    if seg.forced and not is_last:
        return f"{text} {_pick(rng, REACH)} {name(seg.landmark_id)}"
    return f"{text} {_pick(rng, TOWARD)} {name(seg.landmark_id)}"


def template_instruction(request: InstructionRequest, mention_distance: bool = True) -> str:
    """One instruction for one trajectory (see the module docstring)."""
    rng = np.random.default_rng(request.seed)
    segments = merge_short_segments(split_at_transitions(request.actions), request.merge_short_m)
    segments = assign_landmarks(request, segments)
    name = _Mentions(request.landmarks, rng)
    nav = [s for s in segments if s.kind not in (TAKEOFF, LANDING)]
    clauses = []
    if any(s.kind == TAKEOFF for s in segments):
        clauses.append(_pick(rng, PHRASES[TAKEOFF]))
    for i, seg in enumerate(nav):
        clauses.append(_clause(seg, name, rng, mention_distance, is_last=i == len(nav) - 1))
    target = request.target_ids[-1]
    ending = f"{_pick(rng, STOP)} {name(target)}"
    if any(s.kind == LANDING for s in segments):
        ending += f", then {_pick(rng, PHRASES[LANDING])}"
    if not clauses:
        return _sentence(ending)
    text = clauses[0]
    for clause in clauses[1:]:
        text += _pick(rng, CONNECTORS) + clause
    return _sentence(f"{text} and {ending}")


def _sentence(text: str) -> str:
    """Capitalise each sentence start and end with a full stop."""
    parts = [p.strip() for p in text.split(". ")]
    return ". ".join(p[:1].upper() + p[1:] for p in parts if p).rstrip(".") + "."


class TemplateInstructionBackend:
    """The default backend: offline, deterministic per request seed."""

    def __init__(self, mention_distance: bool = True):
        self.mention_distance = mention_distance

    def generate(self, requests: list[InstructionRequest]) -> list[str | None]:
        return [template_instruction(r, self.mention_distance) for r in requests]

    def close(self) -> None:
        pass
