"""bench/analysis/grounding_attributes.py: where a missed centre lands (hand-built boxes), instruction names, the linear
probe on data with and without signal, and the probe of a real (tiny) run."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import run_script

from bench.analysis.grounding_attributes import (
    COLOUR_READINGS,
    LANDINGS,
    READINGS,
    AttributeProbe,
    cell_rank,
    centre_landing,
    named_in,
    probe_accuracy,
    probe_table,
    rank_summary,
)
from openfly_agent.model.config import CellGroundingConfig
from openfly_agent.model.grounding.head import CellGroundingHead
from openfly_agent.sim.scene import Landmark

BOXES = {
    "target": np.array([0.5, 0.5, 0.2, 0.2]),
    "route": np.array([0.2, 0.2, 0.2, 0.2]),
    "big": np.array([0.8, 0.8, 0.4, 0.4]),
    "small": np.array([0.8, 0.8, 0.1, 0.1]),
}


def test_centre_landing_prefers_the_target_then_the_route_then_the_smallest_other_box():
    assert centre_landing((0.5, 0.5), "target", BOXES, ["route"]) == ("target", "target")
    assert centre_landing((0.2, 0.2), "target", BOXES, ["route"]) == ("earlier route landmark", "route")
    # (0.8, 0.8) is inside "big" and "small": the smaller box is the claim
    assert centre_landing((0.8, 0.8), "target", BOXES, ["route"]) == ("other landmark", "small")
    assert centre_landing((0.7, 0.7), "target", BOXES, ["route"]) == ("other landmark", "big")
    assert centre_landing((0.05, 0.95), "target", BOXES, ["route"]) == ("no landmark", None)
    # a target out of view cannot be hit; the box edge is outside (strict)
    assert centre_landing((0.5, 0.5), "gone", {}, []) == ("no landmark", None)
    edge = {"target": np.array([0.5, 0.5, 0.25, 0.25])}  # exact in binary: x = 0.625 is its right edge
    assert centre_landing((0.625, 0.5), "target", edge, []) == ("no landmark", None)
    assert centre_landing((0.6, 0.5), "target", edge, []) == ("target", "target")
    assert set(LANDINGS) == {"target", "earlier route landmark", "other landmark", "no landmark"}


def _landmark(color: str, type_name: str) -> Landmark:
    return Landmark(
        "b1", type_name, color, "mid-rise", "rectangular", "none", (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    )


def test_named_in_needs_colour_then_type_in_one_phrase():
    instruction = "Fly toward the tall red tower with a dome, then turn left to the blue office building."
    assert named_in(instruction, _landmark("red", "tower"))
    assert named_in(instruction, _landmark("blue", "office building"))
    assert not named_in(
        instruction, _landmark("blue", "tower")
    )  # "blue" comes after the tower, in another phrase
    assert not named_in(instruction, _landmark("red", "house"))


def test_probe_reads_a_separable_attribute_and_not_noise():
    rng = np.random.default_rng(0)
    labels = rng.choice(["red", "blue", "gray"], size=400).tolist()
    centres = {"red": [3.0, 0.0], "blue": [0.0, 3.0], "gray": [-3.0, -3.0]}
    signal = np.array([centres[y] for y in labels]) + rng.normal(0, 0.5, size=(400, 2))
    train_acc, test_acc = probe_accuracy(signal[:300], labels[:300], signal[300:], labels[300:])
    assert train_acc > 0.95 and test_acc > 0.95
    noise = rng.normal(size=(400, 16))
    _, test_acc = probe_accuracy(noise[:300], labels[:300], noise[300:], labels[300:])
    assert test_acc < 0.55  # three balanced classes: chance is a third


def test_probe_of_a_tiny_run_reads_every_visible_target(reference_run):
    out, _ = reference_run
    probe = AttributeProbe(out, batch_size=4)
    test = probe.read("test", 8, render=True)
    train = probe.read("train", 8, render=False)
    visible = len(test.attributes["color"])
    assert visible > 0 and sum(test.landings.values()) == visible
    assert test.shared["misses"] == test.landings["other landmark"]
    read = [reading for reading in READINGS if reading not in COLOUR_READINGS]  # no colour vocabulary here
    for reading in READINGS:
        assert len(test.features[reading]) == (visible if reading in read else 0)
    assert test.features["cell pixels"][0].shape == (18,)
    assert (
        len(test.cell_ranks["cell score"]) == visible
        and test.cell_ranks["colour vocabulary: match term"] == []
    )
    rows = probe_table(train, test)
    assert {(r["reading"], r["attribute"]) for r in rows} == {(r, a) for r in read for a in ("color", "type")}
    assert all(
        0.0 <= r["test"] <= 1.0 and 0.0 <= r["majority"] <= 1.0 for r in rows
    )  # train majority on test


def test_bench_script_prints_and_writes_the_figures(reference_run, tmp_path):
    out, _ = reference_run
    report = tmp_path / "attributes.json"
    args = [
        "--run",
        str(out),
        "--max_samples",
        "8",
        "--train_samples",
        "8",
        "--threads",
        "1",
        "--json",
        str(report),
    ]
    done = run_script(args, script=Path(__file__).resolve().parents[2] / "bench" / "grounding_attributes.py")
    assert done.returncode == 0, done.stderr[-2000:]
    figures = json.loads(report.read_text())
    readings = len(READINGS) - len(COLOUR_READINGS)  # the reference run's head has no colour vocabulary
    assert sum(figures["landings"].values()) > 0 and len(figures["probes"]) == 2 * readings
    assert "| landing | share |" in done.stdout and "| head query | color |" in done.stdout
    assert list(figures["target_cell_ranks"]) == ["cell score"] and "| cell score |" in done.stdout


def test_the_target_cells_rank_counts_the_cells_above_it_and_sums_up_as_shares_and_a_median():
    logits = torch.tensor([0.5, 2.0, 0.5, -1.0])
    assert [cell_rank(logits, cell) for cell in range(4)] == [1, 0, 1, 3]  # a tie is not above
    summary = rank_summary([0, 0, 1, 2, 5])  # best 2 of 5, top 3 4 of 5, median rank 1 + 1
    assert summary == {"best": 0.4, "top 3": 0.8, "median": 2.0}


def test_probe_refuses_a_folder_that_is_not_a_run(tmp_path):
    with pytest.raises(FileNotFoundError):
        AttributeProbe(tmp_path)


def test_a_colour_vocabulary_gives_its_histograms_and_asks_as_readings():
    torch.manual_seed(0)
    head = CellGroundingHead(16, CellGroundingConfig(dim=8, num_heads=2, colour_vocabulary=True), grid_side=2)
    probe = AttributeProbe.__new__(AttributeProbe)  # the readings only: no run, no datasets
    probe.agent = SimpleNamespace(network=SimpleNamespace(grounding_head=head))
    pixels = torch.randint(0, 256, (3, 3, 8, 8), dtype=torch.uint8)
    output = SimpleNamespace(word_colours=torch.randn(3, 12))
    with torch.no_grad():
        histograms, asks = probe._colour_vocabulary(pixels, output)
    assert histograms.shape == (3, 4, 13) and asks.shape == (3, 13)  # 12 named colours and none
    torch.testing.assert_close(asks.sum(dim=-1), torch.ones(3))
    head.colour_vocabulary = None
    assert probe._colour_vocabulary(pixels, SimpleNamespace(word_colours=None)) == (None, None)
