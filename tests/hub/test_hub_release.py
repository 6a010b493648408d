"""Model release of the tiny agent: folder layout, sharding, fresh-process trust_remote_code loading that acts
exactly like the source checkpoint, the card's usage code, push + load by repo id through the fake Hub."""

from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from openfly_agent.constants import ACTION_TOKENIZER_NAME, CONFIG_NAME, WEIGHTS_INDEX_NAME, WEIGHTS_NAME
from openfly_agent.hub.config import ModelReleaseConfig
from openfly_agent.hub.fake_hub import FakeHub
from openfly_agent.hub.model_card import split_front_matter
from openfly_agent.hub.model_release import build_model_release, resolve_checkpoint
from openfly_agent.model.persistence.remote_code import AUTO_MAP
from openfly_agent.rollout.checkpoints import checkpoint_fingerprint
from openfly_agent.utils.processes import run_group

REPO_ROOT = Path(__file__).resolve().parents[2]
TOKEN = "hf_releaseTestTokenNeverShown42"
INSTRUCTIONS = [
    "Fly forward to the red skyscraper with a rooftop billboard, then turn left at the tower.",
    "Ascend above the white house and stop near the blue dome.",
    "Turn right after the park and go straight until the spire.",
]
# Runs in this process and, as source text, in fresh processes that never import openfly_agent themselves.
PROBE = textwrap.dedent(
    """
    import hashlib
    import numpy as np

    def rollout(agent, steps=4):
        # 3 episodes x `steps` batched steps on fixed random frames: actions, action logits, boxes
        rng = np.random.RandomState(7)
        episodes = {"e0": INSTRUCTIONS[0], "e1": INSTRUCTIONS[1], "e2": INSTRUCTIONS[2]}
        session = agent.new_session()
        out = []
        for t in range(steps):
            obs = [
                {"episode_id": e, "instruction": text, "pose": (3.0 * t, 0.0, 30.0, 0.0),
                 "rgb": rng.randint(0, 256, (96, 128, 3)).astype(np.uint8)}
                for e, text in episodes.items()
            ]
            for r in session.predict_step(obs):
                logits = r.action_logits.float().tolist()
                out.append({"action": r.action, "logits": logits, "box": list(r.box)})
        return out

    def digest(agent):
        h = hashlib.sha256()
        for name, tensor in sorted(agent.state_dict().items()):
            h.update(name.encode())
            h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
        return h.hexdigest()
    """
).replace("INSTRUCTIONS", repr(INSTRUCTIONS))


def probe_namespace() -> dict:
    namespace: dict = {}
    exec(PROBE, namespace)  # noqa: S102 (our own probe source, shared with the fresh processes)
    return namespace


def assert_same_behaviour(got: list[dict], want: list[dict]) -> None:
    assert [s["action"] for s in got] == [s["action"] for s in want]
    np.testing.assert_allclose([s["logits"] for s in got], [s["logits"] for s in want], rtol=0, atol=1e-5)
    np.testing.assert_allclose([s["box"] for s in got], [s["box"] for s in want], rtol=0, atol=1e-5)


def run_python(code: str, cwd: Path, **env_overrides: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("HF_", "HUGGINGFACE_"))}
    env.update({"HF_HOME": str(cwd / "hf_home"), "HF_HUB_OFFLINE": "1", "PYTHONPATH": str(REPO_ROOT)})
    env.update(env_overrides)
    return run_group([sys.executable, "-c", code], timeout=300, cwd=cwd, env=env, stdin=subprocess.DEVNULL)


def last_json_line(result: subprocess.CompletedProcess):
    assert result.returncode == 0, result.stderr[-4000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A tiny-preset agent saved as a training checkpoint, with its behaviour on the probe."""
    from openfly_agent.model.agent import OpenFlyAgent
    from openfly_agent.model.config import make_model_config
    from openfly_agent.model.language.tokenizer import train_bpe_tokenizer

    root = tmp_path_factory.mktemp("release")
    tokenizer = train_bpe_tokenizer(INSTRUCTIONS * 4, vocab_size=320, out_dir=root / "tokenizer")
    torch.manual_seed(0)
    agent = OpenFlyAgent.from_model_config(make_model_config("tiny"), tokenizer=tokenizer).eval()
    checkpoints = root / "run" / "checkpoints"
    checkpoint = checkpoints / "step-000003"
    agent.save_pretrained(checkpoint)
    (checkpoint / "train_config.json").write_text(
        json.dumps({"seed": 0, "steps": 3, "init": {"checkpoint": None}})
    )
    (checkpoints / "last").write_text("step-000003\n")
    probe = probe_namespace()
    return SimpleNamespace(
        root=root,
        agent=agent,
        checkpoint=checkpoint,
        behaviour=probe["rollout"](agent),
        digest=probe["digest"](agent),
    )


@pytest.fixture(scope="module")
def releases(source):
    """The same checkpoint released unsharded (default 5GB shards) and sharded (1MB)."""
    common = {"repo_id": "me/openfly-tiny", "checkpoint": str(source.root / "run"), "overwrite": True}
    single = build_model_release(ModelReleaseConfig(output_dir=str(source.root / "single"), **common))
    sharded = build_model_release(
        ModelReleaseConfig(output_dir=str(source.root / "sharded"), max_shard_size="1MB", **common)
    )
    return SimpleNamespace(single=single, sharded=sharded)


def test_release_folder_contents(releases, source):
    folder = releases.single
    names = {p.name for p in folder.iterdir()}
    assert {
        CONFIG_NAME,
        WEIGHTS_NAME,
        ACTION_TOKENIZER_NAME,
        "tokenizer.json",
        "tokenizer_config.json",
        "train_config.json",
        "configuration_openfly_agent.py",
        "modeling_openfly_agent.py",
        "README.md",
    } <= names
    assert not [n for n in names if n.endswith((".bin", ".pt", ".pth", ".pkl"))]
    config = json.loads((folder / CONFIG_NAME).read_text())
    assert config["model_type"] == "openfly_agent" and config["auto_map"] == AUTO_MAP
    assert (folder / "train_config.json").read_bytes() == (
        source.checkpoint / "train_config.json"
    ).read_bytes()
    for shim in ("configuration_openfly_agent.py", "modeling_openfly_agent.py"):
        tree = ast.parse((folder / shim).read_text())
        imports = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
        definitions = [n for n in ast.walk(tree) if isinstance(n, (ast.ClassDef, ast.FunctionDef))]
        assert imports and all(m.startswith("openfly_agent.model.") for m in imports)
        assert not definitions  # re-export only: no second copy of the model
    meta, body = split_front_matter((folder / "README.md").read_text())
    assert meta["library_name"] == "transformers" and "model-index" not in meta
    assert "`model.safetensors`" in body


def test_released_weights_follow_the_umask(releases):
    """safetensors writes 0600; the released weights get the mode of a plain file (config.json's, the umask's)."""
    mask = os.umask(0)
    os.umask(mask)
    for folder in (releases.single, releases.sharded):
        weights = sorted(folder.glob("*.safetensors"))
        assert weights
        for path in [*weights, folder / CONFIG_NAME]:
            assert path.stat().st_mode & 0o777 == 0o666 & ~mask, path


def test_sharded_and_unsharded_load_equal_weights(releases, source):
    from openfly_agent.model.agent import OpenFlyAgent

    shards = sorted(p.name for p in releases.sharded.glob("model-*.safetensors"))
    assert len(shards) > 3 and not (releases.sharded / WEIGHTS_NAME).exists()
    index = json.loads((releases.sharded / WEIGHTS_INDEX_NAME).read_text())
    want = source.agent.state_dict()
    saved_names = source.agent.network.state_dict()  # on disk: the released names, no `network.` prefix
    assert set(index["weight_map"]) <= set(saved_names) and set(index["weight_map"].values()) == set(shards)
    digest = probe_namespace()["digest"]
    for folder in (releases.single, releases.sharded):
        loaded = OpenFlyAgent.from_pretrained(str(folder))
        got = loaded.state_dict()
        assert set(got) == set(want)
        for name, tensor in want.items():
            assert torch.equal(got[name], tensor), name
        assert digest(loaded) == source.digest


def test_fresh_process_trust_remote_code_acts_like_the_checkpoint(releases, source, tmp_path):
    code = PROBE + textwrap.dedent(
        f"""
        import json, sys
        from transformers import AutoModel

        assert not [m for m in sys.modules if m.startswith("openfly_agent")]  # nothing imported it
        agent = AutoModel.from_pretrained({str(releases.sharded)!r}, trust_remote_code=True).eval()
        print(json.dumps({{"class": type(agent).__name__, "digest": digest(agent), "steps": rollout(agent)}}))
        """
    )
    result = run_python(code, tmp_path)
    out = last_json_line(result)
    assert out["class"] == "OpenFlyAgent" and out["digest"] == source.digest
    assert_same_behaviour(out["steps"], source.behaviour)
    assert "Do you wish to run the custom code" not in result.stdout + result.stderr


def test_release_accepts_the_last_pointer_and_names_bad_input(source, tmp_path):
    assert resolve_checkpoint(source.root / "run" / "checkpoints" / "last") == source.checkpoint
    assert resolve_checkpoint(source.root / "run") == source.checkpoint
    with pytest.raises(FileNotFoundError, match="not a checkpoint folder"):
        resolve_checkpoint(tmp_path)
    (tmp_path / CONFIG_NAME).write_text(json.dumps({"model_type": "openvla"}))
    with pytest.raises(ValueError, match="model_type is 'openvla'"):
        resolve_checkpoint(tmp_path)
    with pytest.raises(ValueError, match="--lora"):
        ModelReleaseConfig(checkpoint="x", repo_id="me/x", lora="both")


def test_registered_auto_classes_load_without_remote_code(releases, source):
    from transformers import AutoModel

    from openfly_agent.model.agent import register_auto_classes

    register_auto_classes()
    agent = AutoModel.from_pretrained(str(releases.single)).eval()
    assert probe_namespace()["digest"](agent) == source.digest


@pytest.fixture(scope="module")
def pushed(source, tmp_path_factory):
    """`release --push` through the CLI into a fake Hub, then a fresh process loading it by repo id."""
    work = tmp_path_factory.mktemp("push")
    results = work / "results.json"
    results.write_text(json.dumps(_results_json()))
    # what eval.py records beside its results: the fingerprint of the weights it evaluated
    identity = {"policy": "agent", "weights": checkpoint_fingerprint(str(source.checkpoint))}
    (work / "run_identity.json").write_text(json.dumps(identity))
    online = {
        "HF_HUB_OFFLINE": "0",
        "TRANSFORMERS_OFFLINE": "0",
        "HF_TOKEN": TOKEN,
        "OPENFLY_LOG_LEVEL": "DEBUG",
    }
    with FakeHub(token=TOKEN) as hub:
        release = _run_cli(work, hub.url, online, results, source)
        load = run_python(
            PROBE
            + "import json\nfrom transformers import AutoModel\n"
            + "agent = AutoModel.from_pretrained('me/openfly-tiny', trust_remote_code=True).eval()\n"
            + "print(json.dumps({'digest': digest(agent), 'tokenizer': agent.tokenizer is not None}))\n",
            work,
            HF_ENDPOINT=hub.url,
            **online,
        )
        yield SimpleNamespace(
            hub=hub,
            work=work,
            release=release,
            load=load,
            received=hub.files("me/openfly-tiny"),
            folder=work / "release",
        )


def _run_cli(work: Path, endpoint: str, online: dict, results: Path, source) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("HF_", "HUGGINGFACE_"))}
    env.update(HF_HOME=str(work / "hf_home"), PYTHONPATH=str(REPO_ROOT), HF_ENDPOINT=endpoint, **online)
    args = ["release", "--checkpoint", str(source.checkpoint), "--repo_id", "me/openfly-tiny", "--push"]
    args += ["--results", str(results), "--output_dir", str(work / "release"), "--max_shard_size", "2MB"]
    args += ["--card.base_model", "openvla/openvla-7b", "--card.eval_dataset", "me/openfly-embedded"]
    command = [sys.executable, "-m", "openfly_agent.hub", *args]
    return run_group(command, timeout=300, cwd=REPO_ROOT, env=env, stdin=subprocess.DEVNULL)


def _results_json() -> dict:
    overall = {"episodes": 3, "ne_m": 42.5, "sr_pct": 33.25, "osr_pct": 66.5, "spl_pct": 30.0}
    splits = {
        s: {p: {"profile": p, "overall": dict(overall)} for p in ("openfly", "standard")}
        for s in ("test_seen", "test_unseen")
    }
    return {"version": 1, "policy": "agent", "meta": {}, "profiles": {}, "splits": splits}


def test_card_usage_code_runs_against_the_hub(pushed, source, tmp_path):
    """The card's Python block, verbatim, downloads the pushed repo anonymously and acts like the source."""
    body = pushed.received["README.md"].decode()
    [usage] = [b for b in re.findall(r"```python\n(.*?)```", body, flags=re.DOTALL) if "from_pretrained" in b]
    assert 'AutoModel.from_pretrained("me/openfly-tiny", trust_remote_code=True)' in usage
    result = run_python(usage, tmp_path, HF_ENDPOINT=pushed.hub.url, HF_HUB_OFFLINE="0")
    printed = last_json_line(result)
    namespace = {"agent": source.agent, "np": np}
    exec(usage.split("agent.eval()\n", 1)[1], namespace)  # noqa: S102 (same observation, source agent)
    assert printed == namespace["actions"] and len(printed) == 1 and printed[0] in range(10)


def test_push_uploads_the_release_folder(pushed):
    assert pushed.release.returncode == 0, pushed.release.stderr[-4000:]
    local = {
        str(p.relative_to(pushed.folder)): p.read_bytes() for p in pushed.folder.rglob("*") if p.is_file()
    }
    assert pushed.received == local
    assert "pushed: http://127.0.0.1:" in pushed.release.stdout
    meta, _ = split_front_matter(local["README.md"].decode())
    assert meta["base_model"] == "openvla/openvla-7b" and len(meta["model-index"][0]["results"]) == 4
    assert json.loads(local["eval_results.json"]) == _results_json()
    for text in (pushed.release.stdout, pushed.release.stderr, pushed.load.stdout, pushed.load.stderr):
        assert TOKEN not in text
    assert not [p for p in pushed.work.rglob("*") if p.is_file() and TOKEN.encode() in p.read_bytes()]


def test_load_by_repo_id_gives_the_released_weights(pushed, source):
    assert last_json_line(pushed.load)["digest"] == source.digest


def test_load_by_repo_id_brings_the_tokenizer(pushed):
    assert last_json_line(pushed.load)["tokenizer"] is True
