"""Model card: the YAML front matter parses, its model-index equals the eval JSON, bad results are named."""

from __future__ import annotations

import json

import pytest
import yaml

from openfly_agent.hub.config import CardConfig
from openfly_agent.hub.model_card import ModelFacts, render_model_card, split_front_matter
from openfly_agent.hub.results import ResultsError, load_results, parse_results

# Distinct values everywhere, so a metric or profile swapped in the card cannot go unnoticed.
RESULTS = {
    "version": 1,
    "policy": "agent",
    "meta": {"checkpoint": "runs/tiny/checkpoints/last", "sim": "embedded"},
    "profiles": {"openfly": {"name": "openfly", "stop_required": False}, "standard": {"name": "standard"}},
    "splits": {
        split: {
            profile: {
                "profile": profile,
                "overall": {
                    "episodes": 16 + s,
                    "ne_m": 30.0 + 10 * s + p + 0.25,
                    "sr_pct": 12.5 + 10 * s + p,
                    "osr_pct": 40.0 + 10 * s + p,
                    "spl_pct": 11.0 + 10 * s + p + 0.0625,
                    "ndtw_pct": 1.0,
                },
                "per_scene": {},
            }
            for p, profile in enumerate(("openfly", "standard"))
        }
        for s, split in enumerate(("test_seen", "test_unseen"))
    },
}
FACTS = ModelFacts(
    package_version="0.1.0",
    num_parameters="1.23 M",
    action_head="discrete",
    architecture="a small ResNet vision encoder (`tiny-cnn`, 128 px, 8 x 8 tokens per frame)",
    weights_summary="`model.safetensors`",
    release_form="full weights",
    files={"config.json": "model config"},
)


@pytest.fixture
def results_path(tmp_path):
    path = tmp_path / "results.json"
    path.write_text(json.dumps(RESULTS))
    return path


def test_model_index_matches_eval_json(results_path):
    text = render_model_card(
        CardConfig(eval_dataset="me/openfly-embedded"), "me/tiny", load_results(results_path), FACTS
    )
    meta, body = split_front_matter(text)
    assert yaml.safe_load(text.split("---\n")[1]) == meta  # plain YAML parser agrees
    [index] = meta["model-index"]
    assert index["name"] == "tiny"
    blocks = index["results"]
    assert len(blocks) == 4  # test_seen / test_unseen x openfly / standard
    seen = set()
    for block in blocks:
        split = block["dataset"]["split"]
        assert block["dataset"]["type"] == "me/openfly-embedded"
        profiles = {m["config"] for m in block["metrics"]}
        assert len(profiles) == 1
        profile = profiles.pop()
        assert profile in block["task"]["name"]
        expected = RESULTS["splits"][split][profile]["overall"]
        got = {m["type"]: m["value"] for m in block["metrics"]}
        assert got == {
            "ne": expected["ne_m"],
            "sr": expected["sr_pct"],
            "osr": expected["osr_pct"],
            "spl": expected["spl_pct"],
        }
        seen.add((split, profile))
    assert seen == {(s, p) for s in ("test_seen", "test_unseen") for p in ("openfly", "standard")}
    # the body's table states the profile of every number, and the profiles' recorded settings
    # Results without intervals (written before eval recorded them): SR and OSR get the Wilson interval of
    # round(rate * episodes / 100) of the episodes. SR 23.5 % of 17 -> 4 of 17: p = 0.235294, z^2/n = 0.225968,
    # centre = 0.348278 / 1.225968 = 0.284084, half = 1.959964 * sqrt(0.0105842 + 0.0033231) / 1.225968
    # = 0.188535 -> 9.6 .. 47.3 %. OSR 51 % -> 9 of 17: centre = 0.642396 / 1.225968 = 0.523991, half
    # = 1.959964 * sqrt(0.0146550 + 0.0033231) / 1.225968 = 0.214357 -> 31.0 .. 73.8 %. NE and SPL have none.
    assert (
        "| test_unseen | `standard` | **agent** | 17 | 4 of 17 | 41.2 | 23.5 (9.6-47.3) | 51.0 (31.0-73.8) | 22.1 |"
        in body
    )
    assert "Settings used: stop_required=False." in body
    assert "run settings `sim=embedded`" in body  # eval's run meta that changes the numbers


def test_card_shows_the_recorded_intervals_and_counts(tmp_path):
    data = json.loads(json.dumps(RESULTS))
    overall = data["splits"]["test_seen"]["openfly"]["overall"]
    overall.update(
        successes=2, sr_ci95=[3.5, 36.0], osr_ci95=[20.04, 61.96], spl_ci95=[1.0, 20.0], ne_ci95=[20.0, 41.0]
    )
    body = split_front_matter(render_model_card(CardConfig(), "me/tiny", parse_results(data), FACTS))[1]
    assert (
        "| test_seen | `openfly` | **agent** | 16 | 2 of 16 | 30.2 (20.0-41.0) | 12.5 (3.5-36.0) | 40.0 (20.0-62.0) | 11.1 (1.0-20.0) |"
        in body
    )
    bad = json.loads(json.dumps(RESULTS))
    bad["splits"]["test_seen"]["openfly"]["overall"]["sr_ci95"] = [3.5]
    with pytest.raises(ResultsError, match=r"splits.test_seen.openfly.overall.sr_ci95' = \[3.5\]"):
        parse_results(bad)


def test_huggingface_hub_reads_the_card(results_path):
    from huggingface_hub import ModelCard

    text = render_model_card(
        CardConfig(base_model="openvla/openvla-7b"), "me/tiny", load_results(results_path), FACTS
    )
    card = ModelCard(text, ignore_metadata_errors=False)
    assert card.data.license == "mit"
    assert card.data.library_name == "transformers"
    assert card.data.pipeline_tag == "robotics"
    assert card.data.base_model == "openvla/openvla-7b"
    assert {"openfly", "vision-language-navigation", "custom_code"} <= set(card.data.tags)
    assert len(card.data.eval_results) == 16
    sr_unseen_standard = [
        r.metric_value
        for r in card.data.eval_results
        if r.dataset_split == "test_unseen" and r.metric_config == "standard" and r.metric_type == "sr"
    ]
    assert sr_unseen_standard == [23.5]


def test_card_without_results_has_no_model_index():
    text = render_model_card(CardConfig(), "me/tiny", None, FACTS)
    meta, body = split_front_matter(text)
    assert "model-index" not in meta
    assert "No evaluation results" in body


def test_custom_licence_fields():
    card = CardConfig(license="other", license_name="llama2", license_link="LICENSE")
    meta, _ = split_front_matter(render_model_card(card, "me/tiny", None, FACTS))
    assert (meta["license"], meta["license_name"], meta["license_link"]) == ("other", "llama2", "LICENSE")
    with pytest.raises(ValueError, match="license_name"):
        CardConfig(license="other")


def test_odd_strings_stay_valid_yaml():
    card = CardConfig(tags=["a: b", "- dash", "#hash", "quote'\""], eval_dataset_name="x: {y}")
    meta, _ = split_front_matter(render_model_card(card, "me/tiny", parse_results(RESULTS), FACTS))
    assert {"a: b", "- dash", "#hash", "quote'\""} <= set(meta["tags"])
    assert meta["model-index"][0]["results"][0]["dataset"]["name"].startswith("x: {y}")


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda r: r.pop("splits"), r"missing key 'splits'"),
        (
            lambda r: r["splits"].pop("test_seen"),
            r"holds results of test_unseen only; a release needs both test_seen and test_unseen: evaluate with "
            r"eval.py --split=\[test_seen,test_unseen\]",
        ),
        (lambda r: r["splits"]["test_seen"].pop("standard"), r"missing key 'splits.test_seen.standard'"),
        (
            lambda r: r["splits"]["test_seen"]["openfly"]["overall"].update(spl_pct="n/a"),
            r"'splits.test_seen.openfly.overall.spl_pct' = 'n/a' is not a finite number",
        ),
        (
            lambda r: r["splits"]["test_seen"]["openfly"]["overall"].update(ne_m=float("nan")),
            r"overall.ne_m' = nan",
        ),
        (lambda r: r.update(policy="random"), r"policy 'random', not of the agent"),
    ],
)
def test_bad_results_name_file_and_key(tmp_path, mutate, message):
    broken = json.loads(json.dumps(RESULTS))
    mutate(broken)
    path = tmp_path / "results.json"
    path.write_text(json.dumps(broken))
    with pytest.raises(ResultsError, match=message) as err:
        load_results(path)
    assert str(path) in str(err.value)


def test_results_not_json(tmp_path):
    path = tmp_path / "results.json"
    path.write_text("{not json")
    with pytest.raises(ResultsError, match="cannot read"):
        load_results(path)


def test_eval_output_folder_is_accepted(tmp_path):
    (tmp_path / "agent").mkdir()
    (tmp_path / "agent" / "results.json").write_text(json.dumps(RESULTS))
    assert load_results(tmp_path).rows == load_results(tmp_path / "agent" / "results.json").rows
    with pytest.raises(ResultsError, match="without agent/results.json"):
        load_results(tmp_path / "agent")


def test_model_index_of_evals_own_results(tmp_path):
    """eval/report.py results.json from hand-made episode records: the card carries its numbers."""
    from openfly_agent.eval.report import policy_results
    from openfly_agent.rollout.record import EpisodeRecord

    def record(split: str, episode: str, end_x: float, stopped: bool) -> EpisodeRecord:
        return EpisodeRecord(
            split=split,
            episode_id=episode,
            scene_id="embedded-1",
            policy="agent",
            instruction="fly east",
            goal=[60.0, 0.0, 30.0],
            reference_path=[[0.0, 0.0, 30.0], [60.0, 0.0, 30.0]],
            actions=[1] * int(end_x // 3) + ([0] if stopped else []),
            poses=[[3.0 * k, 0.0, 30.0, 0.0] for k in range(int(end_x // 3) + 1)]
            + ([[end_x, 0.0, 30.0, 0.0]] if stopped else []),
            stopped=stopped,
            end_reason="stop" if stopped else "max_steps",
        )

    records = [
        record("test_seen", "a", 60.0, True),  # reaches the goal and stops
        record("test_seen", "b", 30.0, True),  # stops 30 m short
        record("test_unseen", "c", 45.0, False),  # 15 m short, no STOP: success only under `openfly`
    ]
    results = policy_results("agent", records, ["openfly", "standard"])
    path = tmp_path / "results.json"
    path.write_text(json.dumps(results))
    meta, _ = split_front_matter(render_model_card(CardConfig(), "me/tiny", load_results(path), FACTS))
    blocks = meta["model-index"][0]["results"]
    for block in blocks:
        split, profile = block["dataset"]["split"], block["metrics"][0]["config"]
        overall = results["splits"][split][profile]["overall"]
        assert {m["type"]: m["value"] for m in block["metrics"]} == {
            "ne": overall["ne_m"],
            "sr": overall["sr_pct"],
            "osr": overall["osr_pct"],
            "spl": overall["spl_pct"],
        }
    by_key = {(b["dataset"]["split"], b["metrics"][0]["config"]): b for b in blocks}
    sr = {key: next(m["value"] for m in b["metrics"] if m["type"] == "sr") for key, b in by_key.items()}
    ne = {key: next(m["value"] for m in b["metrics"] if m["type"] == "ne") for key, b in by_key.items()}
    assert sr[("test_seen", "openfly")] == sr[("test_seen", "standard")] == 50.0  # hand-checked
    assert (sr[("test_unseen", "openfly")], sr[("test_unseen", "standard")]) == (100.0, 0.0)
    assert ne[("test_seen", "openfly")] == pytest.approx(15.0) and ne[
        ("test_unseen", "standard")
    ] == pytest.approx(15.0)


def test_training_table_from_a_real_train_config():
    from openfly_agent.hub.model_card import summarize_train_config
    from openfly_agent.training.config import TrainConfig
    from openfly_agent.utils.config import config_to_dict

    table = summarize_train_config(config_to_dict(TrainConfig(steps=120)))
    assert "| `steps` | `120` |" in table and "| `optim.lr` | `0.0003` |" in table
    assert "| `batch.global_batch_size` | `16` |" in table
    assert summarize_train_config({"unrelated": 1}) is None


def test_the_network_is_described_from_its_config():
    from openfly_agent.hub.model_card import describe_architecture
    from openfly_agent.model.config import make_model_config

    tiny = describe_architecture(make_model_config("tiny"))
    assert tiny.startswith("a small ResNet vision encoder (`tiny-cnn`, 128 px, 8 x 8 tokens per frame)")
    assert "DINOv2" not in tiny and "FIFO memory of 2 keyframe set(s)" in tiny
    big = describe_architecture(make_model_config("openfly-7b"))
    assert big.startswith(
        "the fused DINOv2 + SigLIP vision encoder (`dinosiglip-224px`, 224 px, 16 x 16 tokens"
    )
    assert "the Llama 2 7B causal LM" in big
    compat = describe_architecture(make_model_config("openvla-compat-7b"))
    assert compat.endswith("it runs the released OpenVLA-format forward (`openvla_history` memory)")


@pytest.mark.parametrize(
    ("trained", "planned", "expected"),
    [
        (1682, 6000, "Trained for 1,682 of the 6,000 configured optimizer steps: the run ended early"),
        (6000, 6000, "Trained for 6,000 optimizer steps, as configured."),
        (250, None, "Trained for 250 optimizer steps (1.0 epochs configured)."),
    ],
)
def test_training_progress_comes_from_the_trainer_state(trained, planned, expected):
    from openfly_agent.hub.model_card import describe_training_progress

    text = describe_training_progress({"steps": planned, "epochs": 1.0}, {"step": trained})
    assert text.startswith(expected)
    assert "unknown" in describe_training_progress({"steps": 6000}, None)


def test_install_line_is_a_clone_never_an_unpublished_pip_version():
    card = render_model_card(CardConfig(), "me/tiny", None, FACTS)
    assert "pip install openfly-agent==" not in card and 'pip install "openfly-agent==' not in card
    assert "pip install -e <clone>" in card
    cloned = render_model_card(
        CardConfig(code_url="https://example.org/openfly-agent.git"), "me/tiny", None, FACTS
    )
    assert (
        "git clone https://example.org/openfly-agent.git openfly-agent\npip install -e ./openfly-agent"
        in cloned
    )


def test_results_of_the_memory_probe_are_not_a_release():
    """`eval.py --agent.memory_probe=empty` is a diagnostic of the memory; its numbers are not the model's."""
    probed = {**RESULTS, "meta": {**RESULTS["meta"], "memory_probe": "empty"}}
    with pytest.raises(ResultsError, match=r"memory probe agent.memory_probe=empty, a diagnostic") as err:
        parse_results(probed, source="r.json")
    assert "\n" not in str(err.value)
    unprobed = {**RESULTS, "meta": {**RESULTS["meta"], "memory_probe": "none"}}
    assert len(parse_results(unprobed).rows) == 4
