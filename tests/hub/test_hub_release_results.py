"""A release tied to its results: eval.py's run identity against the checkpoint, subsamples and baselines on the
card, and a card written from the checkpoint's own config, trainer state and results (end to end, the commands
users type)."""

from __future__ import annotations

import json
import os
import re
from datetime import datetime, timezone
from pathlib import Path
from types import SimpleNamespace

import pytest
from eval_helpers import eval_main, generate_tiny_dataset

from openfly_agent import constants as C
from openfly_agent.hub.cli import main as hub_main
from openfly_agent.hub.model_card import split_front_matter
from openfly_agent.hub.model_release import check_card_files
from openfly_agent.hub.results import ResultsError
from openfly_agent.hub.results_source import check_results_weights
from openfly_agent.rollout.stats import format_interval
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.state import TrainerState

TEXTS = ["fly to the red tower and stop", "turn left at the blue dome then ascend", "descend near the spire"]
CONFIGURED_STEPS, TRAINED_STEPS = 6000, 1682


def _training_run(root: Path, seed: int) -> Path:
    """A tiny-preset (tiny-cnn) agent saved as training saves it: step folder, trainer state, `last` link."""
    import torch

    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.config import make_model_config
    from openfly_agent.model.language.tokenizer import train_bpe_tokenizer

    tokenizer = train_bpe_tokenizer(TEXTS * 8, vocab_size=300, out_dir=None)
    torch.manual_seed(seed)
    agent = OpenFlyAgent.from_model_config(make_model_config("tiny"), tokenizer=tokenizer).eval()
    manager = CheckpointManager(root, keep_last=1)
    staging = manager.begin(TRAINED_STEPS)
    agent.save_pretrained(staging)
    train_config = {
        "stage": "navigation",
        "steps": CONFIGURED_STEPS,
        "seed": seed,
        "init": {"checkpoint": None},
    }
    (staging / C.TRAIN_CONFIG_NAME).write_text(json.dumps(train_config))
    TrainerState(step=TRAINED_STEPS, samples_seen=4 * TRAINED_STEPS).save(staging)
    manager.commit(TRAINED_STEPS)
    return root


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    """Two training runs; eval.py on the first (2 episodes per split, random + agent_true_box beside it)."""
    root = tmp_path_factory.mktemp("release-results")
    dataset = root / "data"
    generate_tiny_dataset(dataset)
    run = _training_run(root / "run", seed=0)
    other = _training_run(root / "other", seed=1)
    out = root / "eval"
    argv = [
        "--checkpoint", str(run / "checkpoints" / "last"), "--baselines=[random,agent_true_box]",
        f"--split=[{C.SPLIT_TEST_SEEN},{C.SPLIT_TEST_UNSEEN}]", "--max_episodes", "2", "--max_steps", "4",
        "--plots=0", "--progress=false", "--torch_threads", "1", f"--dataset_root={dataset}",
        f"--output_dir={out}",
    ]  # fmt: skip
    assert eval_main()(argv) == 0
    return SimpleNamespace(root=root, run=run, other=other, eval=out, dataset=dataset)


def _release(checkpoint: Path, results: Path, out: Path) -> int:
    argv = ["release", "--checkpoint", str(checkpoint), "--repo_id", "me/tiny", "--results", str(results)]
    return hub_main([*argv, "--output_dir", str(out)])


def test_results_of_other_weights_are_refused_naming_both(evaluated, tmp_path, capsys):
    out = tmp_path / "release"
    assert _release(evaluated.other, evaluated.eval, out) == 2
    [line] = capsys.readouterr().err.strip().splitlines()
    assert "evaluated other weights" in line
    assert (
        str((evaluated.run / "checkpoints" / "step-001682").resolve()) in line
    )  # what the results evaluated
    assert str((evaluated.other / "checkpoints" / "step-001682").resolve()) in line  # the checkpoint given
    assert not out.exists()  # refused before anything is written


def test_results_without_a_run_identity_are_refused(evaluated, tmp_path, capsys):
    results = tmp_path / "results.json"
    results.write_text(
        (evaluated.eval / "agent" / C.RESULTS_JSON).read_text()
    )  # copied away from its identity
    assert _release(evaluated.run, results, tmp_path / "release") == 2
    assert "run_identity.json is missing" in capsys.readouterr().err


def test_results_of_one_split_say_that_a_release_needs_both(evaluated, tmp_path, capsys):
    data = json.loads((evaluated.eval / "agent" / C.RESULTS_JSON).read_text())
    del data["splits"][C.SPLIT_TEST_SEEN]  # as `eval.py --split=test_unseen` writes it
    (tmp_path / "eval" / "agent").mkdir(parents=True)
    (tmp_path / "eval" / "agent" / C.RESULTS_JSON).write_text(json.dumps(data))
    assert _release(evaluated.run, tmp_path / "eval", tmp_path / "release") == 2
    [line] = capsys.readouterr().err.strip().splitlines()
    assert line.endswith(
        "holds results of test_unseen only; a release needs both test_seen and test_unseen: evaluate with "
        "eval.py --split=[test_seen,test_unseen] (into the same --output_dir, the episodes already done are kept)"
    ), line
    assert not (tmp_path / "release").exists()


def _ns(moment: datetime) -> int:
    return int(moment.timestamp()) * 10**9


def test_results_of_a_checkpoint_saved_again_name_the_file_and_both_times(tmp_path):
    """Same folder, same size, a later write (a resume that saved the step again): the refusal says which file
    changed and when, in words, not the raw nanosecond modification times of run_identity.json."""
    step = tmp_path / "run" / "checkpoints" / "step-000004"
    step.mkdir(parents=True)
    (step / C.CONFIG_NAME).write_text(json.dumps({"model_type": C.MODEL_TYPE}))
    (step / C.WEIGHTS_NAME).write_bytes(b"w" * 1234)
    then = _ns(datetime(2026, 11, 27, 9, 14, 56, tzinfo=timezone.utc))
    now = _ns(datetime(2026, 11, 27, 10, 2, 11, tzinfo=timezone.utc))
    agent = tmp_path / "eval" / "agent"
    agent.mkdir(parents=True)
    weights = {"folder": str(step.resolve()), "weights": {C.WEIGHTS_NAME: [1234, then]}}
    (agent / "run_identity.json").write_text(json.dumps({"policy": "agent", "weights": weights}))
    os.utime(step / C.WEIGHTS_NAME, ns=(now, now))
    with pytest.raises(ResultsError) as err:
        check_results_weights(agent / C.RESULTS_JSON, step)
    message = str(err.value)
    assert (
        f"its run_identity.json names {step.resolve()} as it was then, and its weights changed since "
        "(model.safetensors was written again: 1,234 B modified 2026-11-27 09:14:56 UTC then, 1,234 B modified "
        "2026-11-27 10:02:11 UTC now); evaluate the checkpoint"
    ) in message
    assert str(then) not in message and str(now) not in message


@pytest.fixture(scope="module")
def card(evaluated):
    out = evaluated.root / "release"
    assert _release(evaluated.run, evaluated.eval, out) == 0
    return split_front_matter((out / "README.md").read_text())


def test_card_says_the_numbers_come_from_a_subsample(card, evaluated):
    meta, body = card
    sizes = {split: len(json.loads((evaluated.dataset / "Annotation" / f"{name}.json").read_text()))
             for split, name in ((C.SPLIT_TEST_SEEN, "seen"), (C.SPLIT_TEST_UNSEEN, "unseen"))}  # fmt: skip
    assert min(sizes.values()) > 2
    for split, total in sizes.items():
        assert re.search(rf"\| {split} \| `openfly` \| \*\*agent\*\* \| 2 of {total} \|", body), split
        assert f"2 of {total} {split} episodes" in body
    assert "`--max_episodes 2`" in body
    assert len(meta["model-index"][0]["results"]) == 4  # the agent's numbers only


def test_card_puts_the_baselines_beside_the_agent(card, evaluated):
    _, body = card
    results = {
        name: json.loads((evaluated.eval / name / C.RESULTS_JSON).read_text())
        for name in ("agent", "random", "agent_true_box")
    }
    for name, data in results.items():
        overall = data["splits"][C.SPLIT_TEST_UNSEEN]["standard"]["overall"]
        shown = "**agent**" if name == "agent" else f"`{name}`"
        row = f"| {C.SPLIT_TEST_UNSEEN} | `standard` | {shown} | 2 of "
        [line] = [line for line in body.splitlines() if line.startswith(row)]
        cells = [
            format_interval(overall[k], overall[f"{k.split('_')[0]}_ci95"])
            for k in ("ne_m", "sr_pct", "osr_pct", "spl_pct")
        ]
        assert line.endswith(
            f"| {overall['successes']} of {overall['episodes']} | " + " | ".join(cells) + " |"
        )
    assert "- `random`: uniformly random actions" in body
    assert "- `agent_true_box`: this model fed the simulator's true target box" in body


def test_card_is_written_from_the_checkpoint(card):
    _, body = card
    assert "a small ResNet vision encoder (`tiny-cnn`, 128 px, 8 x 8 tokens per frame)" in body
    assert "DINOv2" not in body  # not this checkpoint's backbone
    assert f"Trained for {TRAINED_STEPS:,} of the {CONFIGURED_STEPS:,} configured optimizer steps" in body
    assert "pip install openfly-agent==" not in body and 'pip install "openfly-agent==' not in body
    assert "pip install -e <clone>" in body and "not published on PyPI" in body
    assert "reads the text tokenizer from local folders only" not in body  # contradicted docs/RELEASE.md


def test_release_carries_the_trainer_state_and_names_only_its_files(card, evaluated):
    release = evaluated.root / "release"
    step = evaluated.run / "checkpoints" / "step-001682"
    assert (release / C.TRAINER_STATE_NAME).read_bytes() == (step / C.TRAINER_STATE_NAME).read_bytes()
    assert "| `trainer_state.json` |" in card[1]
    check_card_files(release)
