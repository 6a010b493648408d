"""data/generation_settings.py: the typed record of a generated dataset's frame size and cities, and the
datasets generated before it (their full toolchain config only) read to the same values."""

from __future__ import annotations

import json

import pytest

from openfly_agent import constants as C
from openfly_agent.data.generation_settings import GenerationSettings, read_generation_settings
from openfly_agent.utils.errors import RecordError

SETTINGS = GenerationSettings(width=64, height=48, city_size_m=300.0, city_buildings=20)


def _write(root, relative: str, text: str) -> None:
    path = root / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def _old_dataset(root, buildings=20):
    """The toolchain config as datasets generated before the record hold it (an excerpt of its sections)."""
    config = {
        "output_dir": "outputs/datasets/x",
        "render": {"width": 64, "height": 48, "pitch_deg": 0.0},
        "scenes": {"city_size_m": 300.0, "city_buildings": buildings, "train_seeds": [0]},
        "route": {"height_min_m": 10.0},
    }
    _write(root, C.TOOLCHAIN_CONFIG_JSON, json.dumps(config, indent=2, sort_keys=True))


def test_the_record_reads_back_what_was_saved(tmp_path):
    assert SETTINGS.save(tmp_path) == tmp_path / C.GENERATION_SETTINGS_JSON
    assert read_generation_settings(tmp_path) == SETTINGS
    default_city = GenerationSettings(width=128, height=128, city_size_m=1000.0)
    default_city.save(tmp_path)
    assert read_generation_settings(tmp_path) == default_city and default_city.city_buildings is None


def test_a_dataset_generated_before_the_record_reads_to_the_same_values(tmp_path):
    _old_dataset(tmp_path)
    assert read_generation_settings(tmp_path) == SETTINGS
    _old_dataset(tmp_path, buildings=None)  # null: the generator's default
    assert read_generation_settings(tmp_path) == GenerationSettings(64, 48, 300.0, None)


def test_the_record_wins_over_the_old_config(tmp_path):
    _old_dataset(tmp_path)
    GenerationSettings(width=96, height=96, city_size_m=500.0).save(tmp_path)
    assert read_generation_settings(tmp_path) == GenerationSettings(96, 96, 500.0, None)


def test_a_dataset_without_either_record_has_no_settings(tmp_path):
    assert read_generation_settings(tmp_path) is None


@pytest.mark.parametrize(
    "relative, text, field",
    [
        (C.GENERATION_SETTINGS_JSON, '{"width": 64,', "<json>"),
        (C.GENERATION_SETTINGS_JSON, "[64, 48]", "<json>"),
        (C.GENERATION_SETTINGS_JSON, '{"width": 64, "height": 48}', "city_size_m"),
        (C.GENERATION_SETTINGS_JSON, '{"width": "64", "height": 48, "city_size_m": 300}', "width"),
        (C.TOOLCHAIN_CONFIG_JSON, '{"render": {"width": 64}, "scenes": {}}', "height"),
        (C.TOOLCHAIN_CONFIG_JSON, "not json", "<json>"),
    ],
)
def test_a_corrupt_record_is_one_line_naming_the_file_and_field(tmp_path, relative, text, field):
    _write(tmp_path, relative, text)
    with pytest.raises(RecordError) as caught:
        read_generation_settings(tmp_path)
    message = str(caught.value)
    assert message.startswith(f"{tmp_path / relative}: field '{field}'") and "\n" not in message
