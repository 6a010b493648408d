"""The two prompts of the paper's instruction pipeline (paraphrased from the official `ins_gen`).

1. Landmark features: from the frame at the end of a sub-trajectory (or the last 3 frames for the target,
   with the direction of the target in the last one) ask for the prominent landmark as a JSON object
   {color, feature, size, type}.
2. Fusion: combine the scattered actions and landmarks into one instruction, using pronouns for landmarks
   that are mentioned again.
"""

from __future__ import annotations

import json

LANDMARK_KEYS = ("color", "feature", "size", "type")

LANDMARK_SYSTEM = (
    "You annotate data for aerial vision-language navigation. The images come from the front camera of a "
    "drone flying through a city. Identify the nearest prominent landmark (usually a building) in the image "
    "and describe it by its appearance. Answer with one JSON object with exactly the keys "
    '"color", "feature", "size" and "type" (short phrases, e.g. {"color": "red", "feature": "rooftop '
    'billboard", "size": "tall", "type": "office building"}) and nothing else.'
)

TARGET_SYSTEM = (
    "You annotate data for aerial vision-language navigation. The images are the last 3 frames of a drone "
    "flight, oldest first; the drone stops next to its target building. Focus on the LAST image and describe "
    "the target building by its appearance. Answer with one JSON object with exactly the keys "
    '"color", "feature", "size" and "type" (short phrases) and nothing else.'
)

FUSION_SYSTEM = (
    "You write navigation instructions for a drone pilot. You get the scattered actions of one flight in "
    "order, each with the landmark seen when the action ends, as JSON. Combine these scattered actions and "
    "landmarks into one fluent instruction: keep the order of the actions, name each landmark by its "
    "features (color, type, feature), use pronouns for landmarks that are mentioned again, end with the "
    "drone stopping at the last landmark, and answer with the instruction text only."
)


def landmark_user_text() -> str:
    return "What is the nearest prominent landmark in this image?"


def target_user_text(direction: str) -> str:
    """`direction` is left / center / right: where the target's box is in the last image."""
    return f"The target building is at the {direction} of the last image. Describe the target building."


def fusion_user_text(items: list[tuple[str, dict | None]]) -> str:
    """Numbered '<action phrase> to <landmark json>' items, as the official fusion call receives them."""
    lines = []
    for i, (phrase, landmark) in enumerate(items, start=1):
        target = json.dumps(landmark, sort_keys=True) if landmark else "(no landmark)"
        lines.append(f"{i}. {phrase} to {target}")
    return "Scattered actions and landmarks:\n" + "\n".join(lines)


def parse_landmark_json(text: str) -> dict:
    """The first {...} object of a reply, restricted to LANDMARK_KEYS; ValueError when there is none."""
    start, end = text.find("{"), text.rfind("}")
    if start < 0 or end <= start:
        raise ValueError(f"no JSON object in the landmark reply: {text[:120]!r}")
    data = json.loads(text[start : end + 1])
    if not isinstance(data, dict):
        raise ValueError(f"landmark reply is not a JSON object: {text[:120]!r}")
    return {k: str(data[k]) for k in LANDMARK_KEYS if k in data}
