"""The weight average (`optim.ema_decay`, training/ema.py): its update rule by hand, its file, and a run with it
(evaluated and exported weights are the average, the live ones train on, a resume ends where an unbroken run does).
"""

from __future__ import annotations

import pytest
import torch
from conftest import STEPS, checkpoint_weights, make_config, reset_accelerate, train_in_process
from torch import nn

from openfly_agent.training.config import OptimConfig
from openfly_agent.training.ema import (
    EMA_WEIGHTS_NAME,
    load_ema,
    load_live_weights,
    make_ema,
    save_ema,
    update_ema,
)
from openfly_agent.training.state import ACCELERATE_STATE_DIR


@pytest.fixture
def accelerator():
    from accelerate import Accelerator

    reset_accelerate()
    yield Accelerator(cpu=True)
    reset_accelerate()


def _scalar_model(value: float) -> nn.Linear:
    model = nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        model.weight.fill_(value)
    return model


def test_no_decay_means_no_average(accelerator):
    assert make_ema(accelerator, _scalar_model(0.0), None) is None


def test_the_average_copies_at_step_one_then_follows_the_warmed_up_decay(accelerator):
    model = _scalar_model(3.0)
    ema = make_ema(accelerator, model, decay=0.999)
    with torch.no_grad():
        model.weight.fill_(2.0)
    update_ema(ema, accelerator, model, step=1)  # decay 0: the live weights
    assert float(ema.module.weight) == pytest.approx(2.0, abs=1e-7)
    with torch.no_grad():
        model.weight.fill_(0.0)
    # decay at step 20: 1 - 20 ** -0.75 = 0.894260 (by hand: 20^0.75 = 9.4574)
    update_ema(ema, accelerator, model, step=20)
    assert float(ema.module.weight) == pytest.approx(2.0 * 0.894260, abs=1e-5)
    with torch.no_grad():
        model.weight.fill_(1.0)
    ema_before = float(ema.module.weight)
    update_ema(ema, accelerator, model, step=1_000_000)  # warmed-up decay above 0.999: capped at 0.999
    assert float(ema.module.weight) == pytest.approx(0.999 * ema_before + 0.001, abs=1e-6)
    assert not any(p.requires_grad for p in ema.module.parameters())


def test_saved_average_restores_and_a_missing_file_is_named(accelerator, tmp_path):
    model = _scalar_model(1.5)
    ema = make_ema(accelerator, model, decay=0.9)
    path = save_ema(ema, tmp_path)
    assert path.name == EMA_WEIGHTS_NAME
    other = make_ema(accelerator, _scalar_model(-4.0), decay=0.9)
    load_ema(other, tmp_path)
    assert float(other.module.weight) == 1.5
    with pytest.raises(FileNotFoundError, match="ema_decay"):
        load_ema(other, tmp_path / "elsewhere")


@pytest.mark.parametrize("decay", [0.0, 1.0, -0.5])
def test_decay_outside_the_open_unit_interval_is_rejected(decay):
    with pytest.raises(ValueError, match="optim.ema_decay"):
        OptimConfig(ema_decay=decay)


@pytest.fixture(scope="module")
def ema_run(generated_dataset, tmp_path_factory):
    """An unbroken run of STEPS steps with a weight average (a checkpoint every 2 steps)."""
    out = tmp_path_factory.mktemp("ema")
    return out, train_in_process(make_config(generated_dataset, out, steps=STEPS, optim__ema_decay=0.9))


def test_checkpoints_export_the_average_and_keep_the_live_weights(ema_run):
    from safetensors.torch import load_file

    out, result = ema_run
    final = out / "checkpoints" / f"step-{STEPS:06d}"
    exported = checkpoint_weights(final)  # the model folder: what evaluation and the next stage load
    live = checkpoint_weights(final / ACCELERATE_STATE_DIR)  # the trainable tensors the optimizer moves
    saved_average = load_file(str(final / ACCELERATE_STATE_DIR / EMA_WEIGHTS_NAME))
    trained = result.agent.state_dict()
    moved = []
    for key in live:  # the training state's names (`network.*`); the model folder has the released names
        saved = exported[key.removeprefix("network.")]
        torch.testing.assert_close(saved, saved_average[key], rtol=0, atol=0, msg=key)
        torch.testing.assert_close(saved, trained[key], rtol=0, atol=0, msg=key)
        if saved.is_floating_point() and not torch.equal(saved, live[key]):
            moved.append(key)
    assert len(moved) > len(live) // 2, "the model folder should hold the average, not the live weights"
    assert "box_iou" in result.final_metrics


def test_live_weights_replace_the_average_of_a_loaded_checkpoint(ema_run, tmp_path):
    from openfly_agent.model.agent import OpenFlyAgent

    out, _ = ema_run
    final = out / "checkpoints" / f"step-{STEPS:06d}"
    agent = OpenFlyAgent.from_pretrained(str(final))
    live = checkpoint_weights(final / ACCELERATE_STATE_DIR)
    assert load_live_weights(agent, final) == len(live)
    loaded = agent.state_dict()
    for key, value in live.items():
        torch.testing.assert_close(loaded[key], value, rtol=0, atol=0, msg=key)
    with pytest.raises(FileNotFoundError, match="training state"):
        load_live_weights(agent, tmp_path)


def test_resume_with_an_average_ends_where_an_unbroken_run_does(ema_run, generated_dataset, tmp_path):
    out, _ = ema_run
    stopped = train_in_process(
        make_config(generated_dataset, tmp_path, steps=STEPS, optim__ema_decay=0.9), stop_after=3
    )
    assert stopped.stopped_early and stopped.state.step == 3
    resumed = train_in_process(
        make_config(
            generated_dataset,
            tmp_path,
            steps=STEPS,
            resume="true",
            optim__ema_decay=0.9,
            validation__final_eval="false",
        )
    )
    assert resumed.state.step == STEPS
    name = f"step-{STEPS:06d}"
    expected, found = (
        checkpoint_weights(out / "checkpoints" / name),
        checkpoint_weights(tmp_path / "checkpoints" / name),
    )
    assert expected.keys() == found.keys()
    for key in expected:
        torch.testing.assert_close(found[key], expected[key], rtol=0, atol=0, msg=key)
