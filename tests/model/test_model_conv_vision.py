"""The tiny-cnn backbone: token grid, the colour statistics and the patch stem."""

from __future__ import annotations

import pytest
import torch

from openfly_agent.model.config import TinyCnnVisionConfig, TinyVitVisionConfig
from openfly_agent.model.vision.conv import COLOUR_STATS, ConvVisionBackbone, cell_colour_stats

SMALL = {"image_size": 64, "cnn_channels": [16, 16, 16, 32]}  # narrower aborts oneDNN


def _pixels(count: int = 2, size: int = 64) -> torch.Tensor:
    return torch.randint(0, 256, (count, 3, size, size), generator=torch.Generator().manual_seed(0)).to(
        torch.uint8
    )


def test_tokens_form_the_stride_16_grid():
    backbone = ConvVisionBackbone(TinyCnnVisionConfig(**SMALL)).eval()
    assert backbone(_pixels()).shape == (2, 16, 32)  # 64 px / 16 = a 4 x 4 grid of 32-d tokens


def test_cell_colour_stats_by_hand():
    # one 4 x 4 frame of 2 x 2 cells (cell = 2 px, quarters of 1 px): channel 0 counts 0..15, channel 1 is 1
    # in the left column of pixels, channel 2 is constant 5
    x = torch.zeros(1, 3, 4, 4)
    x[0, 0] = torch.arange(16.0).view(4, 4)
    x[0, 1, :, 0] = 1.0
    x[0, 2] = 5.0
    stats = cell_colour_stats(x, 2)  # (1, 18, 2, 2)
    assert stats.shape == (1, COLOUR_STATS, 2, 2)
    # top-left cell: pixels 0, 1, 4, 5 in channel 0; 1, 0, 1, 0 in channel 1; 5 in channel 2
    torch.testing.assert_close(stats[0, :3, 0, 0], torch.tensor([2.5, 0.5, 5.0]))
    torch.testing.assert_close(stats[0, 3:6, 0, 0], torch.tensor([2.0616, 0.5, 0.0010]), atol=1e-4, rtol=0)
    # its quarters are its pixels, channel-major then row-major: channel 0 = 0, 1, 4, 5; channel 1 = 1, 0, 1, 0
    torch.testing.assert_close(stats[0, 6:10, 0, 0], torch.tensor([0.0, 1.0, 4.0, 5.0]))
    torch.testing.assert_close(stats[0, 10:14, 0, 0], torch.tensor([1.0, 0.0, 1.0, 0.0]))
    torch.testing.assert_close(stats[0, 14:18, 0, 0], torch.full((4,), 5.0))
    # bottom-right cell: pixels 10, 11, 14, 15 in channel 0, no left column in channel 1
    torch.testing.assert_close(stats[0, :3, 1, 1], torch.tensor([12.5, 0.0, 5.0]))
    torch.testing.assert_close(stats[0, 6:10, 1, 1], torch.tensor([10.0, 11.0, 14.0, 15.0]))


def test_colour_stats_add_a_projection_of_each_cells_statistics():
    torch.manual_seed(0)
    plain = ConvVisionBackbone(TinyCnnVisionConfig(**SMALL)).eval()
    coloured = ConvVisionBackbone(TinyCnnVisionConfig(**SMALL, cnn_colour_stats=True)).eval()
    coloured.load_state_dict(plain.state_dict(), strict=False)  # same ResNet and position embedding
    assert plain.colour_proj is None and coloured.colour_proj.in_features == COLOUR_STATS
    with torch.no_grad():
        pixels = _pixels()
        extra = coloured(pixels) - plain(pixels)  # (N, 16, 32): only the colour term
        x = (pixels.float() / 255 - torch.tensor([0.485, 0.456, 0.406])[:, None, None]) / torch.tensor(
            [0.229, 0.224, 0.225]
        )[:, None, None]
        cell = x[:, :, 16:32, 48:64]  # token (1, 3) of the 4 x 4 grid: rows 16-31, columns 48-63
        mean, std = cell.mean(dim=(2, 3)), cell.std(dim=(2, 3), unbiased=False)  # (N, 3)
        quarter = x[:, :, 16:24, 56:64].mean(dim=(2, 3))  # its top-right quarter, (N, 3)
        stats = torch.zeros(2, COLOUR_STATS)
        stats[:, :3], stats[:, 3:6] = mean, std
        stats[:, 6:18] = cell_colour_stats(x, 16)[:, 6:, 1, 3]
        torch.testing.assert_close(stats[:, [7, 11, 15]], quarter, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(extra[:, 1 * 4 + 3], coloured.colour_proj(stats), rtol=1e-4, atol=1e-4)
        # the sequences of a frame index read their frame's statistics
        index = torch.tensor([1, 1, 0])
        torch.testing.assert_close(coloured(pixels, frame_index=index), coloured(pixels)[index])
    with pytest.raises(TypeError, match="cnn_colour_stats"):  # a field of the ResNet only
        TinyVitVisionConfig(image_size=112, patch_size=14, cnn_colour_stats=True)


def test_patch4_stem_is_one_4x4_stride_4_conv_into_the_same_first_stage():
    torch.manual_seed(0)
    plain = ConvVisionBackbone(TinyCnnVisionConfig(**SMALL)).eval()
    patch = ConvVisionBackbone(TinyCnnVisionConfig(**SMALL, cnn_stem="patch4")).eval()
    conv = patch.featurizer.conv1
    assert (conv.kernel_size, conv.stride, conv.out_channels) == ((4, 4), (4, 4), 64)
    assert isinstance(patch.featurizer.maxpool, torch.nn.Identity)
    # everything after the stem is the same module tree: the resnet stem's state loads but for conv1's kernel
    missing, unexpected = patch.load_state_dict(
        {k: v for k, v in plain.state_dict().items() if k != "featurizer.conv1.weight"}, strict=False
    )
    assert (missing, unexpected) == (["featurizer.conv1.weight"], [])
    with torch.no_grad():
        x = (_pixels().float() / 255 - torch.tensor([0.485, 0.456, 0.406])[:, None, None]) / torch.tensor(
            [0.229, 0.224, 0.225]
        )[:, None, None]
        # the stem by hand: conv, BN, ReLU, no pool -> (N, 64, 16, 16), a quarter of the 64 px side
        stem = patch.featurizer.act1(
            patch.featurizer.bn1(torch.nn.functional.conv2d(x, conv.weight, stride=4))
        )
        assert stem.shape == (2, 64, 16, 16)
        net = patch.featurizer
        features = net.layer4(net.layer3(net.layer2(net.layer1(stem))))  # (N, 32, 4, 4)
        expected = features.flatten(2).transpose(1, 2) + patch.pos_embed
        torch.testing.assert_close(patch(_pixels()), expected, rtol=1e-4, atol=1e-4)


def test_cnn_stem_choices_and_presets():
    with pytest.raises(ValueError, match="cnn_stem"):
        TinyCnnVisionConfig(**SMALL, cnn_stem="patch8")
    with pytest.raises(TypeError, match="cnn_stem"):  # a field of the ResNet only
        TinyVitVisionConfig(image_size=112, patch_size=14, cnn_stem="patch4")
