"""The grounding section of the model config: the landmark grounding head, one registered choice per head
(`type:` in YAML, `--model.grounding.type=` on the command line), each with only its own fields; stdlib and
draccus only.

Part of the typed model config (model/config.py, which re-exports these names).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from draccus import ChoiceRegistry

from openfly_agent.model.config_checks import check_positive
from openfly_agent.model.config_choice import BuiltChoice

GROUNDING_BOX = "box"  # the paper's box regression (model/grounding/head.py, the 7B presets)
GROUNDING_CELLS = "cells"  # per-cell scoring (`CellGroundingHead`, the tiny preset)
GROUNDING_NONE = "none"  # no head


@dataclass
class GroundingConfig(BuiltChoice, ChoiceRegistry):
    """Landmark grounding: `type` picks the head, `cells` (the default, `CellGroundingConfig`), `box`
    (`BoxGroundingConfig`), or `none` (`NoGroundingConfig`: no head, no box and no grounding loss).

    `build(llm_dim, grid_side)` gives the head of the variant (model/grounding/head.py), None for `none`.
    """

    @classmethod
    def default_choice_name(cls) -> str:
        return GROUNDING_CELLS

    @property
    def type(self) -> str:
        """The registered name of this head (`cells`, `box`, `none`)."""
        return self.get_choice_name(type(self))

    @property
    def has_head(self) -> bool:
        """Whether the model has a grounding head (every type but `none`)."""
        return True


@GroundingConfig.register_subclass(GROUNDING_NONE)
@dataclass
class NoGroundingConfig(GroundingConfig):
    """`none`: no grounding head; the action is read right after the prompt (no box token)."""

    @property
    def has_head(self) -> bool:
        return False


@dataclass
class GroundingHeadConfig(GroundingConfig):
    """The fields of both heads: learned queries cross-attend to the LLM hidden states and give the landmark's box."""

    num_layers: int = 3
    dim: int = 128  # 256 in the 7B preset
    num_heads: int = 4  # 8 in the 7B preset
    loss_weight: float = 1.0  # weight of the grounding loss in the total loss
    l1_weight: float = 1.0  # grounding loss = GIoU + l1_weight * L1 (visible boxes) + visibility_weight * BCE
    visibility_weight: float = (
        0.5  # 0 disables the visibility logit's loss (predicted boxes then always count)
    )

    def __post_init__(self) -> None:
        for name in ("num_layers", "dim", "num_heads"):
            check_positive("grounding", name, getattr(self, name))
        if self.dim % self.num_heads:
            raise ValueError(
                f"grounding.dim={self.dim} must be divisible by grounding.num_heads={self.num_heads}"
            )
        for name in ("loss_weight", "l1_weight", "visibility_weight"):
            if getattr(self, name) < 0:
                raise ValueError(f"grounding.{name} must be >= 0, got {getattr(self, name)}")


@GroundingConfig.register_subclass(GROUNDING_BOX)
@dataclass
class BoxGroundingConfig(GroundingHeadConfig):
    """`box`: the paper's head, an MLP regresses the box from the pooled queries (the 7B presets)."""


@GroundingConfig.register_subclass(GROUNDING_CELLS)
@dataclass
class CellGroundingConfig(GroundingHeadConfig):
    """`cells`: per-cell scoring of the current frame. The query starts from the last prompt token, FiLM-scores
    every cell, the box centre is the softmax-weighted cell centre plus an offset, and `cell_weight` x the
    cross-entropy of the cell holding the box centre joins the loss (`CellGroundingHead`, model/grounding/head.py)."""

    cell_weight: float = 1.0  # weight of the cell cross-entropy
    # at inference: the centre and the size's context come from the (2w + 1) x (2w + 1) cells around the
    # best-scoring one (their softmax renormalised); null: from every cell, as in training (a two-peaked score
    # then puts the centre between two landmarks)
    centre_window: int | None = 1
    # weight of the attribute loss, the cross-entropy of the target landmark's colour, type, size and feature
    # (`TARGET_ATTRIBUTES`, embedded cities only) read from the head's query (what it took from the text) and from
    # the cell under the target's centre (what the frame shows there); 0: no attribute classifiers
    attribute_weight: float = 0.0
    # classes of each attribute (colour, type, size, feature): the embedded city's vocabularies (sim/city_vocab.py)
    attribute_classes: list[int] = field(default_factory=lambda: [12, 6, 3, 8])
    # each cell also gets a projection of the current frame's visual token there (the projector's output, as it
    # enters the LLM), a skip past the LLM, whose layers mix the cells and lose what tells one landmark from
    # another (its colour); false: the cells are the LLM's hidden states only
    visual_skip: bool = False
    # the colour vocabulary (`ColourVocabulary`): a reader of the prompt's words names the target's colour (one of
    # attribute_classes[0], trained on `TARGET_ATTRIBUTES`), each pixel of the current frame is classed as one of
    # those colours or none, and w x log(share of the cell's pixels in the named colour) joins the cell's score,
    # with its own cross-entropy over the cells: a path that keeps a landmark's colour when it covers a few pixels
    colour_vocabulary: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.centre_window is not None and self.centre_window < 0:
            raise ValueError(f"grounding.centre_window must be >= 0 or null, got {self.centre_window}")
        for name in ("cell_weight", "attribute_weight"):
            if getattr(self, name) < 0:
                raise ValueError(f"grounding.{name} must be >= 0, got {getattr(self, name)}")
        if len(self.attribute_classes) != 4 or min(self.attribute_classes) < 2:
            raise ValueError(
                f"grounding.attribute_classes={self.attribute_classes}: 4 counts of >= 2 classes"
            )
