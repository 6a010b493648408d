"""The final evaluation shows its progress and stops on SIGTERM / SIGUSR1 like the training loop does."""

from __future__ import annotations

import importlib.util
import json
import signal
import subprocess
from types import SimpleNamespace

from conftest import REPO_ROOT, make_config, start_script, train_args, train_in_process
from hold_probe import HOLDING

from openfly_agent.utils.processes import communicate_group


def test_a_signal_during_the_final_evaluation_stops_it_and_resume_runs_it(generated_dataset, tmp_path):
    # every test_unseen sample one at a time; tests/hold_probe.py holds the evaluation before its first batch
    # until the signal is received, so the signal lands during it however slow the machine (sending it on the
    # last "checkpoint committed" line raced the evaluation's start under load)
    args = train_args(
        generated_dataset, tmp_path, steps=1, checkpoint__save_interval=0,
        validation__final_max_samples="null", validation__per_device_batch_size=1,
    )  # fmt: skip
    with start_script(
        args, hold="final-eval", stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    ) as process:
        seen = []
        for line in process.stderr:  # the log, line by line, until the final evaluation is held
            seen.append(line)
            if HOLDING in line:
                break
        assert any(HOLDING in line for line in seen), "".join(seen)[-3000:]  # else train.py ended first
        process.send_signal(signal.SIGTERM)
        out, rest = communicate_group(process, timeout=120)
    err = "".join(seen) + rest
    assert process.returncode == 0, err[-3000:]
    assert "SIGTERM received" in err, err[-3000:]
    assert "final evaluation on test_unseen: 139 samples" in err, err[-3000:]
    assert "stopped by a signal during the final evaluation; nothing written as its result" in err
    assert "test:" in err  # its progress bar
    assert " test: " not in err and "offline action accuracy" not in out  # no figures of a partial pass
    logged = [json.loads(line) for line in (tmp_path / "logs" / "metrics.jsonl").read_text().splitlines()]
    assert not [key for record in logged for key in record if key.startswith("test/")]
    assert out.strip() == f"finished at step 1; last checkpoint: {tmp_path / 'checkpoints' / 'step-000001'}"

    # --resume runs the evaluation the signal stopped (on a smaller subset here: validation.* may change)
    resumed = train_in_process(
        make_config(generated_dataset, tmp_path, steps=1, resume="true", validation__final_max_samples=8)
    )
    assert resumed.state.step == 1 and resumed.final_metrics["samples"] == 8


def _train_entry_point():
    spec = importlib.util.spec_from_file_location("train_entry_point", REPO_ROOT / "train.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_final_figures_say_n_a_for_the_box_iou_of_data_without_boxes(capsys):
    report = _train_entry_point().report
    cfg = SimpleNamespace(data=SimpleNamespace(test_split="test_unseen"))
    navigation = {
        "samples": 8.0,
        "action_accuracy": 0.25,
        "majority_class_rate": 0.5,
        "box_iou": float("nan"),
    }
    report(SimpleNamespace(state=SimpleNamespace(step=3), checkpoint="ckpt", final_metrics=navigation), cfg)
    grounding = {"samples": 4.0, "box_iou": float("nan")}
    report(SimpleNamespace(state=SimpleNamespace(step=3), checkpoint="ckpt", final_metrics=grounding), cfg)
    assert capsys.readouterr().out.splitlines()[1::2] == [
        "offline action accuracy on test_unseen (8 samples): 0.2500; majority-class rate: 0.5000; "
        "box IoU: n/a (no boxes in this data)",
        "target box IoU on test_unseen (4 samples): n/a (no boxes in this data)",
    ]
    with_boxes = {**navigation, "box_iou": 0.125}
    report(SimpleNamespace(state=SimpleNamespace(step=3), checkpoint="ckpt", final_metrics=with_boxes), cfg)
    assert capsys.readouterr().out.splitlines()[-1].endswith("; box IoU: 0.1250")
