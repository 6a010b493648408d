"""LoRA checkpoints (training's metadata + `adapter/` layout) released merged or as an adapter."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from test_hub_release import INSTRUCTIONS, assert_same_behaviour, probe_namespace  # tests/hub/ is on sys.path

from openfly_agent.constants import ADAPTER_DIR_NAME, CONFIG_NAME, WEIGHTS_NAME
from openfly_agent.hub.config import CardConfig, ModelReleaseConfig
from openfly_agent.hub.model_card import split_front_matter
from openfly_agent.hub.model_release import build_model_release, check_card_files
from openfly_agent.model.persistence.lora_checkpoint import load_lora_agent
from openfly_agent.training.state import TrainerState


@pytest.fixture(scope="module")
def lora_run(tmp_path_factory):
    """A base checkpoint and a LoRA checkpoint trained on it (adapter, projector moved) as training writes."""
    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.config import LoraSettings, make_model_config
    from openfly_agent.model.language.lora import attach_lora
    from openfly_agent.model.language.tokenizer import train_bpe_tokenizer
    from openfly_agent.training.export import write_lora_folder

    root = tmp_path_factory.mktemp("lora")
    tokenizer = train_bpe_tokenizer(INSTRUCTIONS * 4, vocab_size=320, out_dir=root / "tokenizer")
    torch.manual_seed(1)
    OpenFlyAgent.from_model_config(make_model_config("tiny"), tokenizer=tokenizer).save_pretrained(
        root / "base"
    )
    agent = attach_lora(OpenFlyAgent.from_pretrained(str(root / "base")), LoraSettings(rank=4, alpha=8))
    with torch.no_grad():  # stand-in for training: non-zero adapters, a moved projector
        for name, param in agent.named_parameters():
            if "lora_B" in name or name.startswith("network.projector."):
                param.add_(0.05 * torch.randn_like(param))
    agent.eval()
    checkpoint = root / "run" / "checkpoints" / "step-000010"
    write_lora_folder(agent, agent.state_dict(), checkpoint)
    train_config = {
        "init": {"checkpoint": str(root / "base"), "format": "auto"},
        "data": {"root": "datasets/tiny"},
        "steps": 10,
        "seed": 0,
    }
    (checkpoint / "train_config.json").write_text(json.dumps(train_config))
    TrainerState(step=10, samples_seen=40).save(checkpoint)
    return SimpleNamespace(root=root, checkpoint=checkpoint, behaviour=probe_namespace()["rollout"](agent))


def release(lora_run, form: str, **changes) -> Path:
    cfg = ModelReleaseConfig(
        checkpoint=str(lora_run.checkpoint),
        repo_id=f"me/openfly-tiny-{form}",
        lora=form,
        output_dir=str(lora_run.root / form),
        overwrite=True,
        **changes,
    )
    return build_model_release(cfg)


def test_merged_release_acts_like_the_adapter(lora_run):
    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.language.lora import has_lora

    folder = release(lora_run, "merged")
    assert (folder / WEIGHTS_NAME).is_file() and not (folder / ADAPTER_DIR_NAME).exists()
    assert "auto_map" in json.loads((folder / CONFIG_NAME).read_text())
    agent = OpenFlyAgent.from_pretrained(str(folder)).eval()
    assert not has_lora(agent)
    base = OpenFlyAgent.from_pretrained(str(lora_run.root / "base"))
    trained = agent.network.projector.fc1.weight
    assert not torch.equal(trained, base.network.projector.fc1.weight)  # trained parts are in
    got = probe_namespace()["rollout"](agent)
    assert [s["action"] for s in got] == [s["action"] for s in lora_run.behaviour]
    torch.testing.assert_close(
        torch.tensor([s["logits"] for s in got]),
        torch.tensor([s["logits"] for s in lora_run.behaviour]),
        rtol=0,
        atol=1e-4,  # merging re-associates the float sums
    )


def test_adapter_release_loads_on_its_base(lora_run):
    folder = release(lora_run, "adapter", card=CardConfig(base_model="me/openfly-tiny-base"))
    adapter = folder / ADAPTER_DIR_NAME
    assert {"adapter_config.json", "adapter_model.safetensors", "trainables.safetensors"} <= {
        p.name for p in adapter.iterdir()
    }
    assert not (adapter / "README.md").exists()  # peft's empty template card stays out
    assert not list(folder.glob("model*.safetensors"))  # no full weights
    assert "auto_map" not in json.loads((folder / CONFIG_NAME).read_text())  # nothing AutoModel could load
    assert not (folder / "modeling_openfly_agent.py").exists()
    assert_same_behaviour(
        probe_namespace()["rollout"](load_lora_agent(folder, lora_run.root / "base")), lora_run.behaviour
    )
    meta, body = split_front_matter((folder / "README.md").read_text())
    assert meta["base_model"] == "me/openfly-tiny-base" and meta["base_model_relation"] == "adapter"
    assert "| Weights | LoRA adapter in `adapter/`" in body and "lora" in meta["tags"]
    [usage] = [b for b in re.findall(r"```python\n(.*?)```", body, flags=re.DOTALL) if "load_lora_agent" in b]
    usage = usage.replace('"me/openfly-tiny-adapter"', repr(str(folder)))
    usage = usage.replace('"me/openfly-tiny-base"', repr(str(lora_run.root / "base")))
    namespace: dict = {}
    exec(usage, namespace)  # noqa: S102 (the card's own usage code, ids replaced by local folders)
    assert namespace["actions"][0] in range(10)


def test_lora_errors_say_what_to_pass(lora_run, tmp_path):
    with pytest.raises(ValueError, match="--card.base_model="):
        release(lora_run, "adapter")
    orphan = tmp_path / "orphan"
    shutil.copytree(lora_run.checkpoint, orphan)
    (orphan / "train_config.json").write_text(json.dumps({"init": {"checkpoint": None}}))
    with pytest.raises(ValueError, match="--base_checkpoint"):
        build_model_release(
            ModelReleaseConfig(checkpoint=str(orphan), repo_id="me/x", output_dir=str(tmp_path / "o"))
        )
    wrong_base = tmp_path / "wrong_base"
    shutil.copytree(lora_run.root / "base", wrong_base)
    config = json.loads((wrong_base / CONFIG_NAME).read_text())
    config["agent"]["memory"]["capacity"] = 1
    (wrong_base / CONFIG_NAME).write_text(json.dumps(config))
    cfg = ModelReleaseConfig(
        checkpoint=str(lora_run.checkpoint),
        repo_id="me/x",
        base_checkpoint=str(wrong_base),
        output_dir=str(tmp_path / "w"),
    )
    with pytest.raises(ValueError, match=r"model sections differ at \['memory.capacity: 1 vs 2'"):
        build_model_release(cfg)


@pytest.fixture
def lora_run_folder(lora_run, tmp_path):
    """A LoRA run folder as training lays it out: checkpoints/step-000010 (adapter only), checkpoints/last, and
    merged/, here the base weights themselves, so that what loads tells the merged model from the adapter."""
    run = tmp_path / "run"
    shutil.copytree(lora_run.checkpoint, run / "checkpoints" / "step-000010")
    (run / "checkpoints" / "last").write_text("step-000010\n")
    shutil.copytree(lora_run.root / "base", run / "merged")
    (run / "merged" / CONFIG_NAME).touch()  # written at the end of the run, after its last checkpoint
    return run


def _projector(folder: Path) -> torch.Tensor:
    from safetensors.torch import load_file

    return load_file(str(folder / WEIGHTS_NAME))["projector.fc1.weight"]


@pytest.mark.parametrize("merged", [True, False], ids=["merged", "adapter_on_base"])
def test_eval_loads_a_lora_run_merged_else_adapter_on_base(lora_run, lora_run_folder, merged, caplog):
    from openfly_agent.rollout.checkpoints import load_agent

    if not merged:
        shutil.rmtree(lora_run_folder / "merged")
    with caplog.at_level("INFO", logger="openfly_agent.rollout.checkpoints"):
        agent = load_agent(str(lora_run_folder), "cpu")
    base_projector = _projector(lora_run_folder / "merged" if merged else lora_run.root / "base")
    # merged/ holds the base here; the adapter's run moved the projector away from it
    assert torch.equal(agent.network.projector.fc1.weight, base_projector) == merged
    step = lora_run_folder / "checkpoints" / "step-000010"
    said = "the LoRA run's merged model" if merged else f"the LoRA adapter of {step} on its base"
    assert said in caplog.text


@pytest.mark.parametrize("merged", [True, False], ids=["merged", "adapter_on_base"])
def test_release_of_a_lora_run_takes_its_merged_model_else_adapter_on_base(lora_run, lora_run_folder, merged):
    if not merged:
        shutil.rmtree(lora_run_folder / "merged")
    cfg = ModelReleaseConfig(
        checkpoint=str(lora_run_folder), repo_id="me/x", output_dir=str(lora_run_folder.parent / "release")
    )
    folder = build_model_release(cfg)
    if merged:
        assert torch.equal(_projector(folder), _projector(lora_run_folder / "merged"))
    else:  # the adapter merged into its base: it acts as the adapter did
        from openfly_agent.model.agent import OpenFlyAgent

        got = probe_namespace()["rollout"](OpenFlyAgent.from_pretrained(str(folder)).eval())
        assert [s["action"] for s in got] == [s["action"] for s in lora_run.behaviour]


def test_a_merge_older_than_the_newest_checkpoint_or_an_older_step_is_not_taken(lora_run, lora_run_folder):
    import os

    from openfly_agent.model.persistence.lora_checkpoint import checkpoint_weights

    step = lora_run_folder / "checkpoints" / "step-000010"
    assert checkpoint_weights(step).folder == lora_run_folder / "merged"
    older = step.parent / "step-000005"  # not the step `last` names: the merge holds another one
    shutil.copytree(step, older)
    assert checkpoint_weights(older).base == str(lora_run.root / "base")
    stale = (step / CONFIG_NAME).stat().st_mtime - 60  # a resumed run stopped before writing its merge
    os.utime(lora_run_folder / "merged" / CONFIG_NAME, (stale, stale))
    weights = checkpoint_weights(step)
    assert (weights.folder, weights.base) == (step, str(lora_run.root / "base"))
    assert checkpoint_weights(lora_run_folder / "merged").folder == lora_run_folder / "merged"  # full weights


def _training_section(folder: Path) -> str:
    _, body = split_front_matter((folder / "README.md").read_text())
    return body.split("## Training", 1)[1].split("## Limitations", 1)[0]


@pytest.mark.parametrize("form", ["run_merged", "rebuilt", "adapter"])
def test_a_lora_release_carries_the_run_records_and_says_what_the_fine_tune_was(
    lora_run, lora_run_folder, form
):
    """The run's merged/ holds neither train_config.json nor trainer_state.json: the release takes them from the
    checkpoint it merged, and the card says LoRA (rank, alpha, modules), the base, the data and the steps."""
    step = lora_run_folder / "checkpoints" / "step-000010"
    assert not (lora_run_folder / "merged" / "train_config.json").exists()
    changes = {
        "run_merged": {},
        "rebuilt": {"base_checkpoint": str(lora_run.root / "base")},  # the adapter merged into its base here
        "adapter": {"lora": "adapter", "card": CardConfig(base_model="me/openfly-tiny-base")},
    }[form]
    cfg = ModelReleaseConfig(
        checkpoint=str(lora_run_folder),
        repo_id="me/x",
        output_dir=str(lora_run_folder.parent / form),
        **changes,
    )
    folder = build_model_release(cfg)
    for name in ("train_config.json", "trainer_state.json"):
        assert (folder / name).read_bytes() == (step / name).read_bytes(), name
    training = _training_section(folder)
    # peft resolved all-linear to every Linear of the LLM's layers; the card names each kind once
    modules = "`down_proj`, `gate_proj`, `k_proj`, `o_proj`, `q_proj`, `up_proj`, `v_proj` layers"
    assert f"on the language model's {modules}, the projector and grounding head trained in full" in training
    assert f"a **LoRA fine-tune** of `{lora_run.root / 'base'}`" in training
    assert "rank 4 and alpha 8" in training  # the fixture's LoraSettings(rank=4, alpha=8)
    assert "trained on `datasets/tiny` for 10 optimizer steps" in training
    assert "Trained for 10 optimizer steps, as configured." in training
    _, body = split_front_matter((folder / "README.md").read_text())
    [release_form] = [line for line in body.splitlines() if line.startswith("| Release form |")]
    assert release_form.startswith("| Release form | LoRA adapter"), release_form  # not "full weights"
    check_card_files(folder)  # every release file the card names is in the folder


def test_a_card_naming_a_file_the_release_lacks_is_refused(lora_run, tmp_path):
    folder = release(lora_run, "merged")
    check_card_files(folder)
    (folder / "train_config.json").unlink()
    with pytest.raises(ValueError, match=r"names files the release does not hold: \['train_config.json'\]"):
        check_card_files(folder)
