"""Data cards stay in sync with the code: front matter parses, every column and option is documented."""

from __future__ import annotations

from pathlib import Path

import yaml

from openfly_agent.data.config import MERGED_FORWARD_POSITIONS, TAKEOFF_LANDING_MODES
from openfly_agent.data.parquet_io import TRAJECTORY_SCHEMA

CARDS = Path(__file__).resolve().parents[2] / "data_cards"


def _front_matter(text: str) -> tuple[dict, str]:
    assert text.startswith("---\n")
    meta, body = text[4:].split("\n---\n", 1)
    return yaml.safe_load(meta), body


def test_embedded_card_front_matter_and_schema_table():
    meta, body = _front_matter((CARDS / "embedded.md").read_text())
    assert meta["license"] == "mit" and meta["configs"][0]["config_name"] == "trajectories"
    assert "{{repo_id}}" in body
    for field in TRAJECTORY_SCHEMA:
        assert f"| `{field.name}` |" in body, f"column {field.name} is missing from the schema table"


def test_embedded_card_is_a_valid_dataset_card():
    from huggingface_hub import DatasetCard

    DatasetCard((CARDS / "embedded.md").read_text(), ignore_metadata_errors=False)


def test_released_guide_explains_every_option():
    text = (CARDS / "openfly_released.md").read_text()
    for name in ("takeoff_landing", "merged_forward_position", "strict"):
        assert f"**`{name}`**" in text
    for value in (*TAKEOFF_LANDING_MODES, *MERGED_FORWARD_POSITIONS):
        assert f"`{value}`" in text
