"""training/attribute_targets.py and the attribute loss in training: the lookup gives each landmark its own
vocabulary ids, batches of both stages carry them, and a run logs the attribute loss."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import make_config, train_in_process

from openfly_agent import constants as C
from openfly_agent.model.config import CellGroundingConfig
from openfly_agent.sim.city import COLORS, FEATURES, SIZES, TYPES, CityConfig, generate_city
from openfly_agent.sim.embedded_scenes import EmbeddedScenes
from openfly_agent.toolchain.config import GroundingDataConfig
from openfly_agent.toolchain.grounding import generate_grounding
from openfly_agent.training.attribute_targets import LandmarkAttributes, vocabulary_sizes
from openfly_agent.training.builder import load_splits
from openfly_agent.training.preflight import PreflightError


def test_lookup_gives_the_vocabulary_ids_of_each_landmark():
    config = CityConfig(size_m=300.0, n_buildings=20)
    lookup = LandmarkAttributes(EmbeddedScenes(config))
    buildings = generate_city(5, config).buildings
    for building in buildings[:5]:
        landmark = building.landmark
        expected = [
            list(COLORS).index(landmark.color),
            TYPES.index(landmark.type),
            SIZES.index(landmark.size),
            FEATURES.index(landmark.feature),
        ]
        assert lookup("embedded-5", landmark.landmark_id).tolist() == expected
    assert lookup("embedded-5", "no such landmark").tolist() == [-1, -1, -1, -1]
    assert lookup("real-city/Map", "b1").tolist() == [-1, -1, -1, -1]  # not an embedded city
    assert vocabulary_sizes() == CellGroundingConfig().attribute_classes


def _attribute_run(dataset, out, **overrides):
    return make_config(dataset, out, model__grounding__attribute_weight="1.0", **overrides)


def _read_splits(cfg):
    from conftest import with_val_split

    cfg = with_val_split(cfg)
    return load_splits(cfg.data, cfg.model.grounding)


def test_navigation_batches_carry_the_targets_attributes(generated_dataset, tmp_path):
    from conftest import built_agent, split_batch

    cfg = _attribute_run(generated_dataset, tmp_path / "run")
    splits = _read_splits(cfg)
    step = splits.dataset(C.SPLIT_TRAIN, cfg, built_agent(cfg))[0]
    lookup = LandmarkAttributes.for_dataset(generated_dataset)
    episode = splits.episodes[C.SPLIT_TRAIN][0]
    assert step[C.TARGET_ATTRIBUTES].tolist() == lookup(episode.scene_id, episode.landmark_ids[-1]).tolist()
    batch = split_batch(cfg, built_agent(cfg), C.SPLIT_TRAIN, [0, 1, 2])
    assert batch[C.TARGET_ATTRIBUTES].shape == (3, 4) and bool((batch[C.TARGET_ATTRIBUTES] >= 0).all())


def test_both_stages_train_with_the_attribute_loss(generated_dataset, tmp_path):
    root = tmp_path / "grounding-data"
    generate_grounding(
        GroundingDataConfig(source_root=str(generated_dataset), output_dir=str(root), yaw_copies=0)
    )
    for stage, out in (("grounding", tmp_path / "g"), ("navigation", tmp_path / "n")):
        extra = {"stage": "grounding", "data__grounding_root": str(root)} if stage == "grounding" else {}
        train_in_process(_attribute_run(generated_dataset, out, freeze_stage="full", **extra))
        records = [json.loads(line) for line in (out / "logs" / "metrics.jsonl").read_text().splitlines()]
        losses = [r["train/attribute_loss"] for r in records if "train/attribute_loss" in r]
        assert losses and all(np.isfinite(losses)) and max(losses) > 0, stage


def test_attribute_classes_must_match_the_city_vocabularies(generated_dataset, tmp_path):
    cfg = _attribute_run(
        generated_dataset, tmp_path / "run", model__grounding__attribute_classes="[12,6,3,9]"
    )
    with pytest.raises(PreflightError, match="vocabularies"):
        _read_splits(cfg)


def test_a_dataset_the_toolchain_did_not_make_has_no_attributes(tmp_path):
    with pytest.raises(FileNotFoundError, match="made by the toolchain"):
        LandmarkAttributes.for_dataset(tmp_path)


def test_the_colour_vocabulary_alone_reads_the_attributes_and_trains_its_reader(generated_dataset, tmp_path):
    cfg = make_config(
        generated_dataset, tmp_path / "run", model__grounding__colour_vocabulary="true", freeze_stage="full"
    )
    assert cfg.model.grounding.attribute_weight == 0.0
    assert _read_splits(cfg).attributes is not None  # the reader's labels
    train_in_process(cfg)
    records = [
        json.loads(line) for line in (tmp_path / "run" / "logs" / "metrics.jsonl").read_text().splitlines()
    ]
    losses = [r["train/word_colour_loss"] for r in records if "train/word_colour_loss" in r]
    assert losses and all(np.isfinite(losses)) and max(losses) > 0
    assert not any("train/attribute_loss" in r for r in records)
