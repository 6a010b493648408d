"""Offline BPE tokenizer: special tokens, BOS handling, save / load from a folder."""

from __future__ import annotations

import pytest

from openfly_agent.model.language.tokenizer import load_tokenizer, tiny_vocab_size, train_bpe_tokenizer

TEXTS = [
    "Fly forward to the red skyscraper with a rooftop billboard, then turn left at the tower.",
    "Ascend above the white house and stop near the blue dome.",
    "Turn right after the park and go straight until the spire.",
] * 5


def test_train_save_load(tmp_path):
    tok = train_bpe_tokenizer(TEXTS, vocab_size=300, out_dir=tmp_path / "tok")
    assert 260 <= len(tok) <= 300
    assert (tok.unk_token_id, tok.bos_token_id, tok.eos_token_id, tok.pad_token_id) == (0, 1, 2, 3)
    ids = tok("Turn left at the tower.").input_ids
    assert ids[0] == tok.bos_token_id and tok.eos_token_id not in ids
    assert tok.decode(ids, skip_special_tokens=True).strip() == "Turn left at the tower."
    again = load_tokenizer(tmp_path / "tok")
    assert again("Turn left at the tower.").input_ids == ids
    assert len(again) == len(tok)
    assert tiny_vocab_size(tok) == len(tok) + 256


def test_unseen_characters_are_not_unknown():
    tok = train_bpe_tokenizer(TEXTS, vocab_size=300)
    assert tok.unk_token_id not in tok("Überflug: 42 m → 塔").input_ids


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="too small"):
        train_bpe_tokenizer(TEXTS, vocab_size=100)
    with pytest.raises(FileNotFoundError, match="local folder"):
        load_tokenizer(tmp_path / "missing")
