"""The two grounding heads: the config picks one, both keep the state-dict keys of the single head they replace,
and the paper's regression head initialises (fresh and from OpenVLA weights) and trains in an agent."""

from __future__ import annotations

import pytest
import torch

from openfly_agent.model.config import BoxGroundingConfig, CellGroundingConfig
from openfly_agent.model.grounding.head import BoxRegressionHead, CellGroundingHead, make_grounding_head
from openfly_agent.model.persistence.openvla_loader import (
    agent_from_openvla_checkpoint,
    to_openvla_state_dict,
)

ONE_LAYER = [  # a CrossAttentionLayer's keys
    f"{name}.{kind}"
    for name in ("norm_q", "norm_kv", "q_proj", "k_proj", "v_proj", "out_proj", "norm_mlp", "mlp.0", "mlp.2")
    for kind in ("weight", "bias")
]
# the keys the single `GroundingHead` of earlier checkpoints had (read off it before the split), in its order
SHARED_KEYS = [
    "input_proj.weight",
    "input_proj.bias",
    *(f"layers.0.{key}" for key in ONE_LAYER),
    "norm.weight",
    "norm.bias",
    "visibility.weight",
    "visibility.bias",
]
BOX_MLP_KEYS = ["box_mlp.0.weight", "box_mlp.0.bias", "box_mlp.2.weight", "box_mlp.2.bias"]
REGRESSION_KEYS = ["box_queries", *SHARED_KEYS, *BOX_MLP_KEYS]
CELL_KEYS = [  # every option on: visual skip, attribute classifiers
    "box_queries",
    *SHARED_KEYS,
    "text_query.weight",
    "text_query.bias",
    "visual_proj.weight",
    "visual_proj.bias",
    "cell_scorer.norm.weight",
    "cell_scorer.norm.bias",
    "cell_scorer.scale.weight",
    "cell_scorer.scale.bias",
    "cell_scorer.shift.weight",
    "cell_scorer.shift.bias",
    "cell_scorer.score.1.weight",
    "cell_scorer.score.1.bias",
    "cell_scorer.score.3.weight",
    *BOX_MLP_KEYS,
    "query_attributes.weight",
    "query_attributes.bias",
    "cell_attributes.weight",
    "cell_attributes.bias",
]


def test_the_config_picks_the_head_and_the_keys_stay_those_of_earlier_checkpoints():
    common = {"dim": 16, "num_heads": 2, "num_layers": 1}
    regression = make_grounding_head(24, BoxGroundingConfig(**common), grid_side=2)
    assert type(regression) is BoxRegressionHead
    assert list(regression.state_dict()) == REGRESSION_KEYS
    everything = CellGroundingConfig(
        visual_skip=True,
        attribute_weight=1.0,
        **common,
    )
    cells = make_grounding_head(24, everything, grid_side=2)
    assert type(cells) is CellGroundingHead
    assert list(cells.state_dict()) == CELL_KEYS


def test_the_regression_head_initialises_in_a_fresh_agent_and_trains(make_agent, make_batch):
    agent = make_agent(grounding=BoxGroundingConfig(dim=32, num_heads=2))
    head = agent.network.grounding_head
    assert isinstance(head, BoxRegressionHead) and head.box_queries.std() > 0  # the queries' own init ran
    agent.train()
    loss, logs = agent(make_batch(agent))
    loss.backward()
    assert torch.isfinite(loss) and 0.0 <= logs["box_iou"] <= 1.0
    assert head.box_mlp[2].weight.grad.abs().sum() > 0


@pytest.mark.parametrize("cells", [False, True], ids=["regression", "cells"])
def test_an_agent_starts_from_openvla_weights_with_either_head(
    make_agent, small_config, tiny_tokenizer, tmp_path, cells
):
    from safetensors.torch import save_file

    common = {"dim": 32, "num_heads": 2}
    grounding = CellGroundingConfig(**common, attribute_weight=1.0) if cells else BoxGroundingConfig(**common)
    source = make_agent(grounding=grounding)
    save_file(
        {k: v.contiguous() for k, v in to_openvla_state_dict(source).items()},
        str(tmp_path / "model.safetensors"),
    )
    (tmp_path / "config.json").write_text('{"model_type": "openvla"}')
    agent, report = agent_from_openvla_checkpoint(
        tmp_path, small_config(grounding=grounding), tokenizer=tiny_tokenizer
    )
    head = agent.network.grounding_head
    new = [key for key in report.missing_new if key.startswith("grounding_head.")]
    assert new == sorted(f"grounding_head.{key}" for key in head.state_dict())
    assert all(torch.isfinite(p).all() for p in head.parameters()) and head.box_queries.std() > 0
    torch.testing.assert_close(agent.network.projector.fc1.weight, source.network.projector.fc1.weight)
