"""Referring expressions: a description of one visible landmark that no other visible landmark matches.

The words come from the instruction vocabularies (`instructions/template.py`): size word, colour, type and
feature of the landmark. An expression names a set of attributes; another landmark *matches* it when it has
every named attribute. Colour and type are always named, the feature when the landmark has one, the size word
at random (as instructions do). When another visible landmark still matches, the missing attributes are added;
when even the full description is shared (identical buildings), a relation orders the matching landmarks by
their box centre from left to right: "on the left", "on the right", "in the middle" (of three), or "the k-th
from the left".
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from openfly_agent.sim.scene import Landmark
from openfly_agent.toolchain.instructions.template import feature_phrase, is_named, size_word

ATTRIBUTES = ("size", "color", "type", "feature")  # the order the words appear in
RELATION_LEFT, RELATION_RIGHT, RELATION_MIDDLE = "left", "right", "middle"
_ORDINALS = ("first", "second", "third", "fourth", "fifth", "sixth", "seventh", "eighth", "ninth", "tenth")


@dataclass(frozen=True)
class Expression:
    """One landmark of a frame and the words that single it out.

    Attributes:
        landmark_id: the landmark described.
        text: the referring expression, e.g. "the tall red tower with a spire on the left".
        named: attribute -> value the text names (keys of ATTRIBUTES).
        relation: None, "left", "right", "middle" or "k/n" (k-th of n matching landmarks, from the left).
        box: (cx, cy, w, h) of the landmark in the frame.
    """

    landmark_id: str
    text: str
    named: dict[str, str] = field(default_factory=dict)
    relation: str | None = None
    box: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)


def attribute_values(landmark: Landmark) -> dict[str, str | None]:
    """The nameable attributes of a landmark (None where it has none: unnamed colour, mid-rise, no feature)."""
    return {
        "size": size_word(landmark),
        "color": landmark.color if is_named(landmark.color) else None,
        "type": landmark.type if is_named(landmark.type) else "building",
        "feature": landmark.feature if is_named(landmark.feature) else None,
    }


def matches(named: Mapping[str, str], values: Mapping[str, str | None]) -> bool:
    """Whether a landmark with attribute `values` has every attribute `named`."""
    return all(values.get(key) == value for key, value in named.items())


def _noun_phrase(named: Mapping[str, str], rng: np.random.Generator) -> str:
    words = [named[key] for key in ("size", "color", "type") if key in named]
    text = "the " + " ".join(words)
    if "feature" in named:
        text += " " + feature_phrase(named["feature"], rng)
    return text


def relation_of(rank: int, count: int) -> str:
    """The relation of the landmark at `rank` (0 = leftmost) among `count` identical ones."""
    if rank == 0:
        return RELATION_LEFT
    if rank == count - 1:
        return RELATION_RIGHT
    if count == 3:
        return RELATION_MIDDLE
    return f"{rank + 1}/{count}"


def relation_text(relation: str) -> str:
    """Words of a relation: 'on the left', 'in the middle', ', the second from the left', ..."""
    if relation in (RELATION_LEFT, RELATION_RIGHT):
        return f" on the {relation}"
    if relation == RELATION_MIDDLE:
        return " in the middle"
    rank = int(relation.split("/")[0])
    ordinal = _ORDINALS[rank - 1] if rank <= len(_ORDINALS) else f"{rank}th"
    return f", the {ordinal} from the left"


def describe_uniquely(
    target_id: str, visible: Mapping[str, tuple[Landmark, np.ndarray]], rng: np.random.Generator
) -> Expression:
    """A referring expression for `target_id` that matches no other landmark of `visible`.

    Args:
        target_id: a key of `visible`.
        visible: landmark id -> (landmark, box (cx, cy, w, h)) of every landmark visible in the frame.
        rng: draws the optional size word and the feature phrasing.
    """
    values = {lid: attribute_values(lm) for lid, (lm, _) in visible.items()}
    own = values[target_id]
    named = {key: own[key] for key in ("color", "type", "feature") if own[key] is not None}
    if own["size"] is not None and rng.random() < 0.5:
        named["size"] = own["size"]
    others = [lid for lid in visible if lid != target_id]
    for key in ATTRIBUTES:  # add what is missing while another landmark still matches
        if not any(matches(named, values[o]) for o in others):
            break
        if own[key] is not None:
            named[key] = own[key]
    named = {key: named[key] for key in ATTRIBUTES if key in named}
    relation = None
    rivals = [o for o in others if matches(named, values[o])]
    if rivals:
        group = sorted([target_id, *rivals], key=lambda lid: (float(visible[lid][1][0]), lid))
        relation = relation_of(group.index(target_id), len(group))
    text = _noun_phrase(named, rng) + (relation_text(relation) if relation else "")
    box = tuple(float(v) for v in np.asarray(visible[target_id][1], dtype=np.float64).reshape(4))
    return Expression(target_id, text, named, relation, box)


def frame_expressions(
    visible: Mapping[str, tuple[Landmark, np.ndarray]], rng: np.random.Generator
) -> list[Expression]:
    """One unique expression per visible landmark of a frame, in landmark-id order."""
    return [describe_uniquely(lid, visible, rng) for lid in sorted(visible)]


def resolves_to(expression: Expression, visible: Mapping[str, tuple[Landmark, np.ndarray]]) -> list[str]:
    """The landmarks of `visible` an expression refers to (exactly one for a good expression).

    Reads the expression's named attributes and relation, not its text: the check the tests and the data
    card rely on.
    """
    group = sorted(
        (lid for lid, (lm, _) in visible.items() if matches(expression.named, attribute_values(lm))),
        key=lambda lid: (float(visible[lid][1][0]), lid),
    )
    if expression.relation is None:
        return group
    if expression.relation == RELATION_LEFT:
        return group[:1]
    if expression.relation == RELATION_RIGHT:
        return group[-1:]
    if expression.relation == RELATION_MIDDLE:
        return [group[1]] if len(group) == 3 else []
    rank, count = (int(v) for v in expression.relation.split("/"))
    return [group[rank - 1]] if len(group) == count else []
