"""Model configs written by older code, in today's layout: what `config.json` held before a change to the model
config, read by today's loader (model/pretrained_config.py).

    agent = upgraded_model_dict(json.loads(path.read_text())["agent"])

Before issue 40 the vision backbone, the grounding head and the action head were one flat section each, every
field present whatever the variant (`vision: {preset: tiny-cnn, width: null, ...}`, `grounding: {cells: true,
...}`); they are registered choices now (`vision: {type: tiny-cnn, cnn_channels: ...}`), each variant with only its
own fields. The upgrade names the variant under `type` and drops the other variants' fields where they hold a
value that did nothing (the old config refused any other).

Before issue 46 the LLM, the memory encoding and "no grounding head" were not variants: `llm: {preset: tiny,
hidden_size: 128, ...}` (the four tiny-only sizes null under `llama2-7b`), a top-level `mode: openfly |
openvla_compat` and `grounding: {enabled: false, ...}`. They read `llm: {type: ...}`, `memory: {encoding: {type:
keyframes | openvla_history}}` and `grounding: {type: none}` now. `projector.hidden_ratio` and
`grounding.num_queries` were settings until then, at 4 and 1 in every config; those values are dropped.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from openfly_agent.model.config import (
    ENCODING_KEYFRAMES,
    ENCODING_OPENVLA_HISTORY,
    GROUNDING_NONE,
    ActionHeadConfig,
    GroundingConfig,
    LLMConfig,
    VisionConfig,
)

# Deleted research switches at the value that turned them off (docs/experiments/2026-11-27-deleted-research-switches.md;
# commit 7544758 still has them). A config that holds one at that value loads without it; any other value is
# refused: the checkpoint was trained with code that no longer exists.
DELETED_SWITCHES = {
    "vision": {
        "cnn_fine_fusion": False,
        "cnn_instruction_film": False,
        "cnn_init": "normal",
    },
    "grounding": {
        "subcells": 1,
        "attribute_match": False,
        "dense_attribute_weight": 0.0,
        "cell_fusion_layers": 0,
    },
}
# Settings with one value that no config or experiment ever changed, fixed in the code since issue 46 (the
# projector's fc1 width is OpenVLA's 4 x D_v; one target, one learned grounding query): that value is dropped,
# any other is refused (commit 32e260f still builds it). A section left empty goes with it.
FIXED_SETTINGS = {"projector": {"hidden_ratio": 4}, "grounding": {"num_queries": 1}}
# Switches deleted after the experiment that measured them showed no gain, at the value that turned them off
# (the STOP weight: docs/experiments/2026-11-28-long-route-ablation.md; commit 9046d6d still has it)
DELETED_AFTER_MEASUREMENT = {"action_head": {"stop_loss_weight": 1.0}}
# The auxiliary leg-goal target, deleted after its arm (same log; commit 1cb4fad still has it)
DELETED_LEG_GOAL = {"action_head": {"leg_goal_weight": 0.0}}
# The agent's last actions named in its prompt, deleted after its arm (docs/experiments/
# 2026-11-29-main-job-action-history.md; commit 5925c14 still has it)
DELETED_ACTION_HISTORY = {"prompt": {"action_history": 0}}
# The action trained on the grounding head's own boxes, deleted after its arm (docs/experiments/
# 2026-11-30-main-job-own-boxes.md; commit d6f1b4e still has it)
DELETED_OWN_BOXES = {"action_head": {"box_token_predicted_fraction": 0.0}}
# The colour match (per-pixel colour classes against the colours the grounding query and the prompt's words ask
# for), deleted after its arms (docs/experiments/2026-11-30-main-job-colour-match.md; commit 7dc778f still has it)
DELETED_COLOUR_MATCH = {"grounding": {"colour_match": 0}}
# Each table of retired fields, why a field is gone ({value}: the one it may hold) and the commit that still has it
NO_GAIN = "was deleted (no measured gain; docs/experiments/{log})"
RETIRED_FIELDS = (
    (DELETED_SWITCHES, NO_GAIN.format(log="2026-11-27-deleted-research-switches.md"), "7544758"),
    (DELETED_AFTER_MEASUREMENT, NO_GAIN.format(log="2026-11-28-long-route-ablation.md"), "9046d6d"),
    (DELETED_LEG_GOAL, NO_GAIN.format(log="2026-11-28-long-route-ablation.md"), "1cb4fad"),
    (DELETED_ACTION_HISTORY, NO_GAIN.format(log="2026-11-29-main-job-action-history.md"), "5925c14"),
    (DELETED_OWN_BOXES, NO_GAIN.format(log="2026-11-30-main-job-own-boxes.md"), "d6f1b4e"),
    (DELETED_COLOUR_MATCH, NO_GAIN.format(log="2026-11-30-main-job-colour-match.md"), "7dc778f"),
    (FIXED_SETTINGS, "is fixed at {value} now (no config or experiment changed it)", "32e260f"),
)
# Fields no code read, dropped whatever they hold (timm's plain ResNet stem ignores its width; the action head's
# `n_bins` could only be 256, `NUM_ACTION_SLOTS`).
DEAD_FIELDS = {"vision": ("cnn_stem_width",), "action_head": ("n_bins",)}
# Before the tiny-only size fields defaulted to None, every config.json held the tiny sizes, also under the
# 7B presets (which ignored them). Those exact values are dropped when such a file is read.
LEGACY_TINY_SIZES = {
    "vision": ("tiny", {"width": 96, "fused_width": 128, "depth": 3, "num_heads": 4}),
    "llm": ("tiny", {"hidden_size": 128, "num_layers": 2, "num_heads": 4, "intermediate_size": 344}),
}


ANY = object()  # a field another variant ignored whatever it held
# Fields of the old flat sections that only another variant reads, with the values they held there.
FOREIGN_FIELDS = {
    "vision": {
        "width": (None,), "fused_width": (None,), "depth": (None,), "num_heads": (None,), "cnn_channels": (None,),
        "cnn_colour_stats": (False,), "cnn_stem": ("resnet",),
    },
    "grounding": {
        "cell_weight": ANY, "centre_window": ANY, "attribute_classes": ANY, "attribute_weight": (0.0,),
        "visual_skip": (False,),
    },
    "action_head": {
        "decode_rule": ANY, "unnorm_key": ANY, "box_token": (None, False), "box_token_jitter": ANY,
    },
    "llm": {"hidden_size": (None,), "num_layers": (None,), "num_heads": (None,), "intermediate_size": (None,)},
}  # fmt: skip
CHOICE_SECTIONS = {
    "vision": VisionConfig,
    "grounding": GroundingConfig,
    "action_head": ActionHeadConfig,
    "llm": LLMConfig,
}
# The top-level `mode` of before issue 46 -> the memory encoding it chose.
MODE_ENCODINGS = {"openfly": ENCODING_KEYFRAMES, "openvla_compat": ENCODING_OPENVLA_HISTORY}


class RetiredOptionError(ValueError):
    """An older config turns on a switch that was deleted: its checkpoint needs the code of that time."""


def _drop_retired(agent: dict[str, Any], retired: dict[str, dict[str, Any]], why: str, commit: str) -> None:
    """Drop from `agent` each retired field ({section: {name: the one value it may hold}}) that holds that value,
    and a section left empty; raise `RetiredOptionError` (saying `why` and naming `commit`) for any other value."""
    for section, fields in retired.items():
        values = agent.get(section, {})
        for name, value in fields.items():
            if name in values and values.pop(name) != value:
                raise RetiredOptionError(
                    f"model config: {section}.{name} {why.format(value=value)}: load this checkpoint with "
                    f"commit {commit}"
                )
        if section in agent and not agent[section]:
            del agent[section]


def upgraded_model_dict(agent: dict[str, Any]) -> dict[str, Any]:
    """The model sections of an older `config.json` (`agent`) in today's layout; today's layout is returned as
    it is. Raises `RetiredOptionError` for a deleted switch that is on."""
    agent = {key: dict(value) if isinstance(value, dict) else value for key, value in agent.items()}
    for section, (tiny_preset, sizes) in LEGACY_TINY_SIZES.items():
        values = agent.get(section)
        if isinstance(values, dict) and values.get("preset", tiny_preset) != tiny_preset:
            agent[section] = {k: v for k, v in values.items() if not (k in sizes and v == sizes[k])}
    for retired, why, commit in RETIRED_FIELDS:
        _drop_retired(agent, retired, why, commit)
    for section, names in DEAD_FIELDS.items():
        for name in names:
            agent.get(section, {}).pop(name, None)
    for section in ("vision", "llm"):
        if "preset" in agent.get(section, {}):
            agent[section]["type"] = agent[section].pop("preset")
    if "cells" in agent.get("grounding", {}):
        agent["grounding"]["type"] = "cells" if agent["grounding"].pop("cells") else "box"
    if agent.get("grounding", {}).pop("enabled", True) is False:
        agent["grounding"] = {"type": GROUNDING_NONE}  # the head's fields did nothing without it
    if agent.get("mode") in MODE_ENCODINGS:
        encoding = MODE_ENCODINGS[agent.pop("mode")]
        if encoding != ENCODING_KEYFRAMES:  # the default
            agent["memory"] = {**agent.get("memory", {}), "encoding": {"type": encoding}}
    for section, registry in CHOICE_SECTIONS.items():
        values = agent.get(section)
        if not values or values.get("type") not in registry.get_known_choices():
            continue  # a variant the loader will name as unknown
        own = {f.name for f in dataclasses.fields(registry.get_choice_class(values["type"]))}
        for name, inert in FOREIGN_FIELDS[section].items():
            if name in values and name not in own and (inert is ANY or values[name] in inert):
                del values[name]
    return agent
