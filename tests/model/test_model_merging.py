"""Visual token merging and grid pooling (model/memory/merging.py) on constructed inputs."""

from __future__ import annotations

import pytest
import torch

from openfly_agent.model.memory.merging import choose_reference, grid_pool, merge_into_reference


def _random_frames(n=2, s=3, p=16, d=8):
    return torch.randn(n, s, p, d)


def test_identical_frames_collapse_into_the_reference():
    ref = torch.randn(2, 1, 16, 8)
    frames = ref.expand(2, 4, 16, 8).clone()
    mask = torch.ones(2, 4, dtype=torch.bool)
    out = merge_into_reference(frames, mask, torch.tensor([1, 3]), threshold=0.9)
    torch.testing.assert_close(out, ref[:, 0], rtol=0, atol=1e-6)


def test_orthogonal_tokens_never_merge():
    basis = torch.eye(8)  # 8 orthonormal directions
    reference = basis[:4][None, None]  # tokens e0..e3
    other = basis[4:][None, None] * 3.0  # tokens e4..e7: orthogonal to every reference token
    frames = torch.cat([reference, other], dim=1)  # (1, 2, 4, 8)
    out = merge_into_reference(frames, torch.ones(1, 2, dtype=torch.bool), torch.tensor([0]), threshold=0.1)
    torch.testing.assert_close(out, reference[:, 0], rtol=0, atol=0)


def test_averaging_is_exact():
    # reference tokens r0 = (1, 0), r1 = (0, 1); comparative frame A token (3, 0) -> r0, token (0, -1) never
    # (cosine -1); frame B token (2, 0.0) -> r0, token (0, 5) -> r1.
    reference = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    frame_a = torch.tensor([[3.0, 0.0], [0.0, -1.0]])
    frame_b = torch.tensor([[2.0, 0.0], [0.0, 5.0]])
    frames = torch.stack([frame_a, reference, frame_b])[None]  # (1, 3, 2, 2), reference in the middle
    out = merge_into_reference(frames, torch.ones(1, 3, dtype=torch.bool), torch.tensor([1]), threshold=0.5)
    expected = torch.tensor([[(1 + 3 + 2) / 3, 0.0], [0.0, (1 + 5) / 2]])
    torch.testing.assert_close(out[0], expected, rtol=0, atol=0)


def test_padding_frames_never_merge():
    frames = _random_frames()
    mask = torch.tensor([[True, False, False], [True, True, False]])
    frames[0, 1] = frames[0, 0]  # a padded copy of the reference: must not count
    out = merge_into_reference(frames, mask, torch.tensor([0, 0]), threshold=-1.0)
    torch.testing.assert_close(out[0], frames[0, 0])
    # threshold -1 merges every real comparative token: frame 1 of set 1 goes somewhere, frame 2 nowhere
    assert not torch.allclose(out[1], frames[1, 0])


def test_top_r_limits_merges_per_frame():
    ref = torch.randn(1, 1, 16, 8)
    frames = torch.cat([ref, ref.clone()], dim=1)
    frames[0, 1] += 0.01 * torch.randn(16, 8)  # near copy: every token has a partner
    mask = torch.ones(1, 2, dtype=torch.bool)
    out_r0 = merge_into_reference(frames, mask, torch.tensor([0]), threshold=None, top_r=0)
    torch.testing.assert_close(out_r0, ref[:, 0], rtol=0, atol=0)
    out_r3 = merge_into_reference(frames, mask, torch.tensor([0]), threshold=None, top_r=3)
    changed = (out_r3[0] != ref[0, 0]).any(dim=-1)
    assert int(changed.sum()) == 3


def test_batched_merge_equals_per_set_merge():
    frames = _random_frames(n=4, s=5, p=16, d=8)
    frames[:, 2] = frames[:, 0] + 0.05 * torch.randn(4, 16, 8)
    mask = torch.rand(4, 5) > 0.3
    mask[:, 0] = True
    refs = torch.tensor([0, 2, 0, 4])
    mask[torch.arange(4), refs] = True
    batched = merge_into_reference(frames, mask, refs, threshold=0.8)
    for i in range(4):
        single = merge_into_reference(frames[i : i + 1], mask[i : i + 1], refs[i : i + 1], threshold=0.8)
        torch.testing.assert_close(batched[i : i + 1], single)


def test_choose_reference():
    boxes = torch.tensor(
        [
            [[0.5, 0.5, 0.2, 0.2], [0.5, 0.5, 0.6, 0.6], [0.5, 0.5, 0.9, 0.9]],  # 3rd is larger but invisible
            [[0.5, 0.5, 0.1, 0.1]] * 3,  # no visible box: middle real frame
            [[0.5, 0.5, 0.4, 0.4], [0.5, 0.5, 0.4, 0.4], [0.5, 0.5, 0.1, 0.1]],  # tie: earliest
        ]
    )
    visible = torch.tensor([[True, True, False], [False, False, False], [True, True, True]])
    mask = torch.tensor([[True, True, True], [False, True, True], [True, True, True]])
    assert choose_reference(boxes, visible, mask).tolist() == [1, 2, 0]


def test_grid_pool_shapes_and_values():
    tokens = torch.arange(16, dtype=torch.float32).reshape(1, 16, 1)  # 4x4 grid, value = row * 4 + col
    pooled = grid_pool(tokens, 2)
    assert pooled.shape == (1, 4, 1)
    assert pooled[0, :, 0].tolist() == [2.5, 4.5, 10.5, 12.5]  # mean of each 2x2 block
    assert grid_pool(tokens, 4)[0, 0, 0].item() == 7.5
    torch.testing.assert_close(grid_pool(tokens, 1), tokens)
    assert grid_pool(torch.randn(3, 256, 5), 16).shape == (3, 1, 5)
    with pytest.raises(ValueError, match="divide"):
        grid_pool(tokens, 3)
