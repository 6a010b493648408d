"""The instruction code (mean prompt embedding) and its FiLM parameters, by hand."""

from __future__ import annotations

import torch

from openfly_agent.model.language.sequence import left_pad_ids
from openfly_agent.model.vision.instruction_film import InstructionFiLM, mean_prompt_embedding


def test_mean_prompt_embedding_averages_the_prompt_positions_only():
    embeds = torch.tensor([[[1.0, 2.0], [3.0, 4.0], [100.0, 100.0]], [[5.0, 6.0], [7.0, 8.0], [9.0, 10.0]]])
    mask = torch.tensor([[True, True, False], [False, False, True]])
    torch.testing.assert_close(mean_prompt_embedding(embeds, mask), torch.tensor([[2.0, 3.0], [9.0, 10.0]]))
    assert mean_prompt_embedding(embeds, torch.zeros(2, 3, dtype=torch.bool)).abs().sum() == 0  # no NaN


def test_left_pad_ids():
    ids, mask = left_pad_ids([[5, 6, 7], [8], []])
    assert ids.tolist() == [[5, 6, 7], [0, 0, 8], [0, 0, 0]]
    assert mask.tolist() == [[True, True, True], [False, False, True], [False, False, False]]


def test_film_starts_at_identity_and_pairs_scale_and_shift_per_stage_input():
    film = InstructionFiLM(text_dim=8, widths=(3, 2))
    film.reset_to_identity()
    (scale_a, shift_a), (scale_b, shift_b) = film(torch.randn(4, 8))
    assert scale_a.shape == (4, 3, 1, 1) and shift_b.shape == (4, 2, 1, 1)
    assert bool((scale_a == 1).all() and (shift_a == 0).all() and (scale_b == 1).all())
    with torch.no_grad():
        film.net[-1].bias.copy_(torch.arange(10.0))  # [gamma_a (3) | beta_a (3) | gamma_b (2) | beta_b (2)]
        (scale_a, shift_a), (scale_b, shift_b) = film(torch.zeros(1, 8))
    assert scale_a.flatten().tolist() == [1.0, 2.0, 3.0] and shift_a.flatten().tolist() == [3.0, 4.0, 5.0]
    assert scale_b.flatten().tolist() == [7.0, 8.0] and shift_b.flatten().tolist() == [8.0, 9.0]
