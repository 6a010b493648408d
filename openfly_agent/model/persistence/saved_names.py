"""The agent's parameter names on disk: OpenVLA's (`vision_backbone.*`, `projector.*`, `language_model.*`, plus
`grounding_head.*`, `box_token_embed.*`), without the `network.` of the agent's child module (model/agent.py).

Model folders (releases, training checkpoints), LoRA adapters and merged exports keep those names, so folders
written before the network was a child module load unchanged and new ones load in older code: transformers' save
/ load maps them through the conversion mapping registered here (`register_saved_names`, reverted on save), the
LoRA adapter and the OpenVLA loader read and write `agent.network.state_dict()` (whose names they are) and
gathered state dicts go through `saved_state_dict`. Resume files (the training state, the weight average) hold
`agent.state_dict()` as it is; `agent.load_state_dict` also takes the saved names (`accept_saved_names`), so
those written before load too.
"""

from __future__ import annotations

from transformers.conversion_mapping import register_checkpoint_conversion_mapping
from transformers.core_model_loading import WeightRenaming

NETWORK_PREFIX = "network."  # the agent's child module holding every parameter
SAVED_PARTS = ("vision_backbone", "projector", "language_model", "grounding_head", "box_token_embed")


def saved_name(name: str) -> str:
    """`network.projector.fc1.weight` -> `projector.fc1.weight` (a name without the prefix is kept)."""
    return name.removeprefix(NETWORK_PREFIX)


def live_name(name: str) -> str:
    """`projector.fc1.weight` -> `network.projector.fc1.weight`."""
    return NETWORK_PREFIX + name


def saved_state_dict(state_dict: dict) -> dict:
    """An agent state dict under the names on disk."""
    return {saved_name(key): value for key, value in state_dict.items()}


def accept_saved_names(module, state_dict: dict, prefix: str, *args) -> None:
    """`load_state_dict` pre-hook of the agent: rename `<prefix><part>.*` to `<prefix>network.<part>.*` in place."""
    for key in [
        k for k in state_dict if k.startswith(prefix) and k[len(prefix) :].split(".", 1)[0] in SAVED_PARTS
    ]:
        state_dict[prefix + live_name(key[len(prefix) :])] = state_dict.pop(key)


def register_saved_names(model_type: str) -> None:
    """Have transformers load `<part>.*` into `network.<part>.*` and save it back as `<part>.*` for `model_type`
    (called once when model/agent.py is imported; registering again replaces it)."""
    register_checkpoint_conversion_mapping(
        model_type,
        [WeightRenaming(rf"^{part}\.", f"{NETWORK_PREFIX}{part}.") for part in SAVED_PARTS],
        overwrite=True,
    )
