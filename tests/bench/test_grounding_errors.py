"""bench/analysis/grounding_errors.py: the breakdown of the target boxes' errors, checked on hand-built boxes."""

from __future__ import annotations

import math

import pytest
import torch

from bench.analysis.grounding_errors import centre_inside, errors_markdown, grounding_errors

TARGET = torch.tensor([[0.5, 0.5, 0.2, 0.2], [0.2, 0.2, 0.1, 0.1]])  # areas 0.04 and 0.01
PRED = torch.tensor([[0.5, 0.5, 0.4, 0.2], [0.8, 0.8, 0.1, 0.1]])  # twice as wide on target; elsewhere
CELLS = torch.tensor([[0.0, 0.0, 0.0, 5.0], [0.0, 1.0, 0.0, 5.0]])  # 2 x 2 grid, argmax cell 3 for both


def test_hand_built_boxes_give_the_hand_computed_breakdown():
    errors = grounding_errors(PRED, TARGET, CELLS)
    # box 1: intersection 0.04, union 0.08 -> IoU 0.5, centre inside, area x2; with its true size IoU 1
    # box 2: no overlap -> IoU 0, centre outside, same area; with its true centre IoU 1, with its true size 0
    assert errors["count"] == 2
    assert errors["mean_iou"] == pytest.approx(0.25)
    assert errors["iou_at_least_0_5"] == pytest.approx(0.5) and errors["iou_zero"] == pytest.approx(0.5)
    assert errors["centre_inside"] == pytest.approx(0.5)
    assert errors["iou_centre_inside"] == pytest.approx(0.5) and errors["iou_centre_outside"] == 0.0
    assert errors["log_area_ratio"] == pytest.approx(math.log(2) / 2, abs=1e-6)
    assert errors["abs_log_area_ratio"] == pytest.approx(math.log(2) / 2, abs=1e-6)
    assert errors["iou_true_centre"] == pytest.approx((0.5 + 1.0) / 2)
    assert errors["iou_true_size"] == pytest.approx((1.0 + 0.0) / 2)
    # target cells on the 2 x 2 grid: (0.5, 0.5) -> cell 3, (0.2, 0.2) -> cell 0; argmax 3 for both
    assert errors["cell_exact"] == pytest.approx(0.5) and errors["cell_within_one"] == pytest.approx(1.0)
    bins = {(b["area_min"], b["area_max"]): b for b in errors["by_area"]}
    assert bins[(0.0, 0.02)]["count"] == 1 and bins[(0.0, 0.02)]["mean_iou"] == 0.0
    assert bins[(0.02, 0.06)]["count"] == 1 and bins[(0.02, 0.06)]["mean_iou"] == pytest.approx(0.5)
    assert bins[(0.02, 0.06)]["centre_inside"] == 1.0
    assert all(b["count"] == 0 and math.isnan(b["mean_iou"]) for k, b in bins.items() if k[0] >= 0.06)
    # offsets |cx - 0.5| of the targets: 0 (box 1) and 0.3 (box 2, on the bin's lower edge)
    offsets = {(b["offset_min"], b["offset_max"]): b for b in errors["by_offset"]}
    assert offsets[(0.0, 0.1)]["count"] == 1 and offsets[(0.0, 0.1)]["mean_iou"] == pytest.approx(0.5)
    assert offsets[(0.3, 0.4)]["count"] == 1 and offsets[(0.3, 0.4)]["mean_iou"] == 0.0
    assert offsets[(0.3, 0.4)]["centre_inside"] == 0.0
    assert sum(b["count"] for b in errors["by_offset"]) == 2


def test_exact_predictions_are_perfect_and_the_last_bins_are_closed():
    full = torch.tensor([[0.5, 0.5, 1.0, 1.0]])  # the whole frame: area 1, the last edge
    errors = grounding_errors(full, full)
    assert errors["mean_iou"] == pytest.approx(1.0) and errors["centre_inside"] == 1.0
    assert errors["log_area_ratio"] == 0.0 and "cell_exact" not in errors
    assert errors["by_area"][-1]["count"] == 1
    at_the_edge = torch.tensor([[1.0, 0.5, 0.1, 0.1]])  # centred on the right edge: offset 0.5, the last edge
    assert grounding_errors(at_the_edge, at_the_edge)["by_offset"][-1]["count"] == 1


def test_no_visible_target_gives_nan_means_not_an_error():
    errors = grounding_errors(torch.zeros(0, 4), torch.zeros(0, 4), torch.zeros(0, 64))
    assert errors["count"] == 0 and math.isnan(errors["mean_iou"]) and math.isnan(errors["cell_exact"])


def test_centre_inside_is_strict_at_the_box_edge():
    target = torch.tensor([[0.5, 0.5, 0.2, 0.2]] * 2)
    pred = torch.tensor([[0.6, 0.5, 0.1, 0.1], [0.59, 0.59, 0.1, 0.1]])  # on the right edge; just inside
    assert centre_inside(pred, target).tolist() == [False, True]


def test_markdown_shows_the_figures_and_every_area_bin():
    text = errors_markdown(grounding_errors(PRED, TARGET, CELLS), title="run")
    assert text.startswith("### run\n")
    assert (
        "| mean IoU | 0.250 |" in text and "| argmax cell: exact / within one cell | 50.0% / 100.0% |" in text
    )
    assert "| 0-0.02 | 1 | 0.000 | 0.0% |" in text and "| 0.4-1 | 0 | nan | nan% |" in text
    assert "| 0-0.1 | 1 | 0.500 | 100.0% |" in text and "| 0.3-0.4 | 1 | 0.000 | 0.0% |" in text
    assert "| 0.4-0.5 | 0 | nan | nan% |" in text
