"""The grounding section of the model config: the landmark grounding head and its loss weights; stdlib only.

Part of the typed model config (model/config.py, which re-exports `GroundingConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from openfly_agent.model.config_checks import check_positive


@dataclass
class GroundingConfig:
    """Landmark grounding head: learned queries cross-attend to the LLM hidden states and regress a box.

    `cells` (the tiny preset) adds per-cell scoring of the current frame: the query starts from the last prompt
    token, FiLM-scores every cell, the box centre is the softmax-weighted cell centre plus an offset, and
    `cell_weight` x the cross-entropy of the cell holding the box centre joins the loss (model/grounding/head.py).
    """

    enabled: bool = True
    num_layers: int = 3
    num_queries: int = 1
    dim: int = 128  # 256 in the 7B preset
    num_heads: int = 4  # 8 in the 7B preset
    loss_weight: float = 1.0  # weight of the grounding loss in the total loss
    l1_weight: float = 1.0  # grounding loss = GIoU + l1_weight * L1 (visible boxes) + visibility_weight * BCE
    visibility_weight: float = (
        0.5  # 0 disables the visibility logit's loss (predicted boxes then always count)
    )
    cells: bool = True  # per-cell scoring and box centre (False: the paper's box regression, the 7B presets)
    cell_weight: float = 1.0  # weight of the cell cross-entropy (with `cells`)
    # with `cells`, at inference: the centre and the size's context come from the (2w + 1) x (2w + 1) cells around
    # the best-scoring one (their softmax renormalised); null: from every cell, as in training (a two-peaked score
    # then puts the centre between two landmarks). Checkpoints older than the option load with the default.
    centre_window: int | None = 1
    # with `cells`: weight of the attribute loss, the cross-entropy of the target landmark's colour, type, size and
    # feature (`TARGET_ATTRIBUTES`, embedded cities only) read from the head's query (what it took from the text)
    # and from the cell under the target's centre (what the frame shows there); 0: no attribute classifiers
    attribute_weight: float = 0.0
    # classes of each attribute (colour, type, size, feature): the embedded city's vocabularies (sim/city_vocab.py)
    attribute_classes: list[int] = field(default_factory=lambda: [12, 6, 3, 8])
    # with `cells`: each cell also gets a projection of the current frame's visual token there (the projector's
    # output, as it enters the LLM), a skip past the LLM, whose layers mix the cells and lose what tells
    # one landmark from another (its colour); false: the cells are the LLM's hidden states only
    visual_skip: bool = False

    def __post_init__(self) -> None:
        for name in ("num_layers", "num_queries", "dim", "num_heads"):
            check_positive("grounding", name, getattr(self, name))
        if self.centre_window is not None and self.centre_window < 0:
            raise ValueError(f"grounding.centre_window must be >= 0 or null, got {self.centre_window}")
        if self.dim % self.num_heads:
            raise ValueError(
                f"grounding.dim={self.dim} must be divisible by grounding.num_heads={self.num_heads}"
            )
        weights = ("loss_weight", "l1_weight", "visibility_weight", "cell_weight", "attribute_weight")
        for name in weights:
            if getattr(self, name) < 0:
                raise ValueError(f"grounding.{name} must be >= 0, got {getattr(self, name)}")
        if len(self.attribute_classes) != 4 or min(self.attribute_classes) < 2:
            raise ValueError(
                f"grounding.attribute_classes={self.attribute_classes}: 4 counts of >= 2 classes"
            )
        if self.visual_skip and not self.cells:
            raise ValueError("grounding.visual_skip needs grounding.cells (it adds to the scored cells)")
        if self.attribute_weight and not self.cells:
            raise ValueError("grounding.attribute_weight needs grounding.cells (the target's cell is read)")
