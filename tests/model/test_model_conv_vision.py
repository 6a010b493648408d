"""The tiny-cnn backbone: token grid, and the stride-8 fusion's layout (each token gets its own 2 x 2 cells)."""

from __future__ import annotations

import pytest
import torch

from openfly_agent.model.conv_vision import ConvVisionBackbone
from openfly_agent.model.vision_config import VisionConfig

SMALL = {"image_size": 64, "cnn_channels": [16, 16, 16, 32], "cnn_stem_width": 16}  # narrower aborts oneDNN


def _pixels(count: int = 2, size: int = 64) -> torch.Tensor:
    return torch.randint(0, 256, (count, 3, size, size), generator=torch.Generator().manual_seed(0)).to(
        torch.uint8
    )


def test_tokens_form_the_stride_16_grid():
    backbone = ConvVisionBackbone(VisionConfig(**SMALL)).eval()
    assert backbone.fine_proj is None
    assert backbone(_pixels()).shape == (2, 16, 32)  # 64 px / 16 = a 4 x 4 grid of 32-d tokens


def test_fine_fusion_adds_each_tokens_own_stride_8_cells():
    torch.manual_seed(0)
    plain = ConvVisionBackbone(VisionConfig(**SMALL)).eval()
    fused = ConvVisionBackbone(VisionConfig(**SMALL, cnn_fine_fusion=True)).eval()
    fused.load_state_dict(plain.state_dict(), strict=False)  # same ResNet and position embedding
    assert fused.fine_proj.in_features == 4 * 16
    with torch.no_grad():
        torch.nn.init.normal_(fused.fine_proj.weight)
        pixels = _pixels()
        extra = fused(pixels) - plain(pixels)  # (N, 16, 32): only the fusion term
        x = (pixels.float() / 255 - torch.tensor([0.485, 0.456, 0.406])[:, None, None]) / torch.tensor(
            [0.229, 0.224, 0.225]
        )[:, None, None]
        _, (stage2,) = plain.featurizer.forward_intermediates(x, indices=[2])  # (N, 16, 8, 8)
        for row, col in [(0, 0), (1, 3), (3, 2)]:
            cells = stage2[
                :, :, 2 * row : 2 * row + 2, 2 * col : 2 * col + 2
            ]  # (N, 16, 2, 2) under the token
            expected = fused.fine_proj(
                cells.reshape(2, 16 * 4)
            )  # channel-major, as pixel_unshuffle orders it
            torch.testing.assert_close(extra[:, row * 4 + col], expected, rtol=1e-4, atol=1e-4)


def test_fine_fusion_is_a_tiny_cnn_option():
    with pytest.raises(ValueError, match="tiny-cnn option"):
        VisionConfig(preset="tiny", image_size=112, patch_size=14, cnn_fine_fusion=True)


def _film_backbone(scale: float = 0.0) -> ConvVisionBackbone:
    """A conditioned backbone (8-d codes); `scale` > 0 gives its FiLM a random non-zero last layer."""
    torch.manual_seed(0)
    backbone = ConvVisionBackbone(VisionConfig(**SMALL, cnn_instruction_film=True), text_dim=8).eval()
    backbone.instruction_film.reset_to_identity()
    if scale:
        torch.nn.init.normal_(backbone.instruction_film.net[-1].weight, std=scale)
    return backbone


def test_instruction_film_at_identity_gives_the_plain_features_of_each_sequences_frame():
    backbone = _film_backbone()
    plain = ConvVisionBackbone(VisionConfig(**SMALL)).eval()
    plain.load_state_dict(backbone.state_dict(), strict=False)  # same ResNet and position embedding
    pixels, frame_index = _pixels(2), torch.tensor([1, 0, 1])
    with torch.no_grad():
        conditioned = backbone(pixels, torch.randn(3, 8), frame_index)  # (3, 16, 32)
        expected = plain(pixels)[frame_index]
    torch.testing.assert_close(conditioned, expected, rtol=1e-5, atol=1e-5)


def test_instruction_film_changes_the_features_with_the_instruction_only():
    backbone = _film_backbone(scale=0.5)
    pixels, codes = _pixels(1), torch.randn(2, 8, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        a, b = backbone(pixels, codes, torch.tensor([0, 0]))  # one frame, two instructions
        again = backbone(pixels, codes[:1])[0]  # the first instruction alone
    assert (a - b).abs().max() > 1e-3
    torch.testing.assert_close(a, again, rtol=1e-5, atol=1e-5)


def test_instruction_film_needs_its_code_and_is_a_tiny_cnn_option():
    with pytest.raises(ValueError, match="instruction code"):
        _film_backbone()(_pixels(1))
    with pytest.raises(ValueError, match="instruction code"):
        ConvVisionBackbone(VisionConfig(**SMALL)).eval()(_pixels(1), torch.zeros(1, 8))
    with pytest.raises(ValueError, match="tiny-cnn option"):
        VisionConfig(preset="tiny", image_size=112, patch_size=14, cnn_instruction_film=True)
    with pytest.raises(ValueError, match="choose one"):
        VisionConfig(**SMALL, cnn_fine_fusion=True, cnn_instruction_film=True)
