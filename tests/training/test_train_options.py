"""train.py's option surface: what `--help` lists, and the settings that left it (derived, duplicated, test-only)
still read from a run's stored train_config.json."""

from __future__ import annotations

import pytest

from openfly_agent.training.cli import help_text
from openfly_agent.training.config import REMOVED_SETTINGS, TrainConfig, without_removed_settings
from openfly_agent.utils.config import config_from_dict, config_to_dict, flat_settings

MAX_OPTIONS = 89  # issue 46: under 90 options in `train.py --help`
# the options outside `--model.*` (`--config_path` included): 65 before issue 46 took out stop_after_steps,
# tokenizer.path, init.format, data.train_split and logging.run_name (60); the RL stage's section added 14
MAX_TRAINING_OPTIONS = 74


def help_options() -> list[str]:
    """The flags `python train.py --help` lists (its lines that start with `--`)."""
    return [line.split()[0] for line in help_text([]).splitlines() if line.lstrip().startswith("--")]


def test_the_training_sections_list_only_what_a_user_sets():
    options = help_options()
    training = [option for option in options if not option.startswith("--model.")]
    assert len(training) <= MAX_TRAINING_OPTIONS, training
    assert not {f"--{key}" for key in REMOVED_SETTINGS} & set(options)


@pytest.mark.xfail(
    strict=True,
    reason="issue 46 item 4: 126 listed after the registered variants and the RL section; next lever: list a "
    "stage's or choice's section only where it applies (rl.* under --stage=rl); remove this mark then",
)
def test_train_help_lists_fewer_than_90_options():
    assert len(help_options()) <= MAX_OPTIONS


def test_a_stored_config_with_removed_settings_still_reads():
    stored = config_to_dict(TrainConfig())
    stored["stop_after_steps"] = 3
    stored["tokenizer"]["path"] = "/some/tokenizer"
    stored["init"]["format"] = "auto"
    stored["data"]["train_split"] = "train"
    stored["logging"]["run_name"] = "a-run"
    assert set(REMOVED_SETTINGS) <= set(flat_settings(stored))
    with pytest.raises(ValueError, match="TrainConfig"):  # an unknown key
        config_from_dict(TrainConfig, stored)
    assert config_from_dict(TrainConfig, without_removed_settings(stored)) == TrainConfig()
    assert stored["tokenizer"]["path"] == "/some/tokenizer"  # the stored dict is left as it was
