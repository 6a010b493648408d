"""Action tokenizer: both heads round-trip all 10 actions; OpenVLA bin arithmetic checked by hand."""

from __future__ import annotations

import json

import numpy as np
import pytest

from openfly_agent.constants import MODEL_ACTION_IDS, OPENVLA_ACTION_VECTORS
from openfly_agent.model.language.action_tokenizer import CODEBOOK, ActionTokenizer, select_action_stats

VOCAB_END = 32000
EOS = 2


def _codebook_stats() -> dict:
    """Stats of a dataset that uses every action once: q01 = 0 and q99 = the largest code per dim."""
    return {
        "q01": [0.0] * 8,
        "q99": CODEBOOK.max(axis=0).tolist(),
        "min": [0.0] * 8,
        "max": CODEBOOK.max(axis=0).tolist(),
    }


def _bins(decode_rule: str = "exact", stats: dict | None = None) -> ActionTokenizer:
    return ActionTokenizer(
        "openvla_bins",
        VOCAB_END,
        eos_token_id=EOS,
        action_stats=stats or _codebook_stats(),
        decode_rule=decode_rule,
    )


def test_codebook_is_the_official_table():
    assert CODEBOOK.shape == (10, 8)
    assert CODEBOOK[0].tolist() == [1, 0, 0, 0, 0, 0, 0, 0]  # stop
    assert CODEBOOK[9].tolist() == [0, 9, 0, 0, 0, 0, 0, 0]  # forward 9
    assert CODEBOOK[2].tolist() == [0, 0, 15, 0, 0, 0, 0, 0]  # turn left (code 15, executed 30 deg)


@pytest.mark.parametrize("action", MODEL_ACTION_IDS)
def test_discrete_round_trip(action):
    tok = ActionTokenizer("discrete", vocab_end=1280)
    ids = tok.action_to_token_ids(action)
    assert ids == [1280 - 256 + action]
    assert tok.token_ids_to_action(ids) == action


def test_discrete_ids_are_in_the_last_256():
    tok = ActionTokenizer("discrete", vocab_end=VOCAB_END)
    assert tok.discrete_token_ids == tuple(range(31744, 31754))
    assert tok.is_action_token(np.array(tok.discrete_token_ids)).all()
    with pytest.raises(ValueError, match="not one of the discrete action ids"):
        tok.token_ids_to_action([31743])


@pytest.mark.parametrize("rule", ["exact", "nearest"])
@pytest.mark.parametrize("action", MODEL_ACTION_IDS)
def test_bins_round_trip_all_actions(action, rule):
    tok = _bins(rule)
    ids = tok.action_to_token_ids(action)
    assert len(ids) == 9 and ids[-1] == EOS
    assert all(31744 <= i <= 31999 for i in ids[:8])
    assert tok.token_ids_to_action(ids) == action
    # the decoded vector is the official codebook vector after rounding
    vector = tok.unnormalize(tok.token_ids_to_vector(np.array(ids[:8])))
    assert np.round(vector).tolist() == list(OPENVLA_ACTION_VECTORS[action])


def test_bin_arithmetic_by_hand():
    tok = _bins()
    # +1 -> digitize 256 -> id 31744; -1 -> digitize 1 -> id 31999; 0 -> digitize 128 -> id 31872
    assert tok.vector_to_token_ids(np.array([1.0, -1.0, 0.0, 5.0, -5.0, 0.5, 0, 0])) == [
        31744,
        31999,
        31872,
        31744,
        31999,
        32000 - 192,
        31872,
        31872,
    ]
    centres = tok.token_ids_to_vector(np.array([31744, 31999, 31872, 32000]))
    # id 31744 -> bin 256 -> index clipped to 254 (the edge quirk); 31999 -> index 0; 31872 -> index 127 = 0.0
    assert centres[0] == pytest.approx(1 - 1 / 255)
    assert centres[1] == pytest.approx(-1 + 1 / 255)
    assert centres[2] == pytest.approx(0.0, abs=1e-12)
    assert centres[3] == pytest.approx(-1 + 1 / 255)  # id = vocab_end -> index -1 clipped to 0


def test_exact_rule_falls_back_to_stop_and_nearest_does_not():
    almost_turn_left = np.array([0, 0, 13.2, 0, 0, 0, 0, 0.4])
    assert _bins("exact").vector_to_action(almost_turn_left) == 0
    assert _bins("nearest").vector_to_action(almost_turn_left) == 2


def test_vlnv1_style_stats_can_never_ascend():
    """q01 = q99 = 0 on the up/down dims (docs/OFFICIAL_OPENFLY.md 1.6): ascend encodes to +1 but decodes to 0 -> STOP."""
    stats = _codebook_stats()
    stats["q99"][4] = stats["q99"][5] = 0.0
    stats.pop("min"), stats.pop("max")
    tok = _bins("exact", stats)
    assert tok.token_ids_to_action(tok.action_to_token_ids(4)) == 0
    assert tok.token_ids_to_action(tok.action_to_token_ids(1)) == 1


def test_bins_without_stats_or_eos_is_a_clear_error():
    with pytest.raises(ValueError, match="eos_token_id"):
        ActionTokenizer("openvla_bins", VOCAB_END)
    tok = ActionTokenizer("openvla_bins", VOCAB_END, eos_token_id=EOS)
    with pytest.raises(ValueError, match="norm stats"):
        tok.action_to_token_ids(1)
    with pytest.raises(ValueError, match="take-off/landing"):
        _bins().action_to_token_ids(-1)


def test_select_action_stats():
    stats = {"vlnv1": {"action": _codebook_stats()}, "vln_norm": {"action": _codebook_stats()}}
    assert select_action_stats(stats, "vlnv1") is stats["vlnv1"]["action"]
    assert select_action_stats({}, None) is None
    with pytest.raises(ValueError, match="unnorm_key"):
        select_action_stats(stats, None)
    with pytest.raises(ValueError, match="not in norm_stats"):
        select_action_stats(stats, "nope")


def test_save_and_load(tmp_path):
    tok = _bins("nearest")
    tok.save(tmp_path / "action_tokenizer.json")
    data = json.loads((tmp_path / "action_tokenizer.json").read_text())
    again = ActionTokenizer.from_dict(data, action_stats=_codebook_stats())
    assert again.to_dict() == tok.to_dict()
    assert [again.action_to_token_ids(a) for a in MODEL_ACTION_IDS] == [
        tok.action_to_token_ids(a) for a in MODEL_ACTION_IDS
    ]
