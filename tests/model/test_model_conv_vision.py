"""The tiny-cnn backbone: token grid, the stride-8 fusion's layout (each token gets its own 2 x 2 cells), the
instruction FiLM, the colour statistics and the ResNet's init."""

from __future__ import annotations

import pytest
import torch

from openfly_agent.model.vision.config import VisionConfig
from openfly_agent.model.vision.conv import COLOUR_STATS, ConvVisionBackbone, cell_colour_stats

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
    plain = ConvVisionBackbone(VisionConfig(**SMALL)).eval()
    coloured = ConvVisionBackbone(VisionConfig(**SMALL, cnn_colour_stats=True)).eval()
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
    with pytest.raises(ValueError, match="tiny-cnn option"):
        VisionConfig(preset="tiny", image_size=112, patch_size=14, cnn_colour_stats=True)


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


def _resnet(make_agent, cnn_init: str) -> torch.nn.Module:
    """The ResNet of a fresh agent (default stage widths 32-64-96-128) after the agent's own init."""
    return make_agent(vision=VisionConfig(image_size=64, cnn_init=cnn_init)).vision_backbone.featurizer


def test_cnn_init_timm_gives_kaiming_convs_and_blocks_that_start_as_their_shortcut(make_agent):
    timm_init, normal = _resnet(make_agent, "timm"), _resnet(make_agent, "normal")
    # Kaiming normal, fan-out, ReLU gain: std = sqrt(2 / (k * k * out_channels))
    expected = {
        "conv1": (2 / (7 * 7 * 64)) ** 0.5,  # timm's plain stem: 7 x 7 to 64 channels, 0.0253
        "layer1.0.conv1": (2 / (3 * 3 * 32)) ** 0.5,  # 0.0833
        "layer4.0.conv2": (2 / (3 * 3 * 128)) ** 0.5,  # 0.0417
        "layer2.0.downsample.0": (2 / (1 * 1 * 64)) ** 0.5,  # 1 x 1 shortcut, 0.177
    }
    for name, std in expected.items():
        assert timm_init.get_submodule(name).weight.std().item() == pytest.approx(std, rel=0.1), name
        assert normal.get_submodule(name).weight.std().item() == pytest.approx(0.02, rel=0.1), name
    for layer in ("layer1", "layer2", "layer3", "layer4"):
        block = f"{layer}.0"
        assert torch.all(timm_init.get_submodule(f"{block}.bn2").weight == 0), block
        assert torch.all(normal.get_submodule(f"{block}.bn2").weight == 1), block
        assert torch.all(timm_init.get_submodule(f"{block}.bn1").weight == 1), block


def test_cnn_init_leaves_loaded_weights_alone(make_agent, tmp_path):
    from openfly_agent.model.agent import OpenFlyAgent

    agent = make_agent(vision=VisionConfig(image_size=64, cnn_init="timm"))
    with torch.no_grad():  # as after training: no longer what a fresh init gives
        for parameter in agent.vision_backbone.parameters():
            parameter.add_(0.5)
    agent.save_pretrained(tmp_path)
    loaded = OpenFlyAgent.from_pretrained(tmp_path).vision_backbone.state_dict()
    own = agent.vision_backbone.state_dict()
    assert own.keys() == loaded.keys() and all(torch.equal(own[k], loaded[k]) for k in own)


def test_cnn_init_choices_and_presets():
    with pytest.raises(ValueError, match="cnn_init"):
        VisionConfig(**SMALL, cnn_init="kaiming")
    with pytest.raises(ValueError, match="tiny-cnn option"):
        VisionConfig(preset="tiny", image_size=112, patch_size=14, cnn_init="timm")


def test_patch4_stem_is_one_4x4_stride_4_conv_into_the_same_first_stage():
    torch.manual_seed(0)
    plain = ConvVisionBackbone(VisionConfig(**SMALL)).eval()
    patch = ConvVisionBackbone(VisionConfig(**SMALL, cnn_stem="patch4")).eval()
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
        VisionConfig(**SMALL, cnn_stem="patch8")
    with pytest.raises(ValueError, match="tiny-cnn option"):
        VisionConfig(preset="tiny", image_size=112, patch_size=14, cnn_stem="patch4")
