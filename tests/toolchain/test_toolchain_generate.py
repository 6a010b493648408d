"""End to end: generate a small dataset with the embedded simulator and check it against the simulator.

Every trajectory replays through the dynamics without collision to within the success radius of its goal,
the stored boxes are the renderer's instance-buffer boxes, the instructions name the target's attributes,
and resume / shards / summary behave.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
from types import SimpleNamespace

import numpy as np
import pytest

from openfly_agent import constants as C
from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.frames import FrameStore
from openfly_agent.data.generation_settings import GenerationSettings, read_generation_settings
from openfly_agent.data.openfly_reader import load_openfly_dataset
from openfly_agent.sim import dynamics
from openfly_agent.sim.city import generate_city, parse_scene_id
from openfly_agent.toolchain.config import (
    CategoryConfig,
    DaggerConfig,
    GenerateConfig,
    RenderConfig,
    RouteConfig,
    SceneConfig,
)
from openfly_agent.toolchain.generate import generate
from openfly_agent.toolchain.ledger import UnitLedger
from openfly_agent.toolchain.scenes import city_config_for
from openfly_agent.toolchain.worker import default_simulator
from openfly_agent.utils.geometry import Pose

KEEP = ReaderOptions(takeoff_landing="keep")


def small_config(root, **scene_kw) -> GenerateConfig:
    scenes = SceneConfig(
        **{"city_size_m": 300, "city_buildings": 30, "train_seeds": [0], "unseen_seeds": [1],
           "trajectories_per_scene": 6, "test_seen_fraction": 0.3, **scene_kw}
    )  # fmt: skip
    route = RouteConfig(
        height_min_m=10, height_max_m=40, min_dist_m=40, max_dist_m=90,
        with_turn_prob=0.3, chain_prob=0.3, takeoff_landing_prob=0.3,
    )  # fmt: skip
    return GenerateConfig(
        output_dir=str(root),
        workers=0,
        scenes=scenes,
        route=route,
        categories=CategoryConfig(height_bins_m=[25, 40], length_bins_m=[50, 100]),
        render=RenderConfig(width=64, height=64),
        dagger=DaggerConfig(episodes_per_scene=2, max_policy_steps=5),
        plots=False,
    )


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("generated")
    cfg = small_config(root)
    summary = generate(cfg, progress=False)
    return cfg, root, summary


def _episodes(root):
    return {split: load_openfly_dataset(root, split, KEEP) for split in C.SPLITS}


def test_dataset_has_all_splits_and_a_consistent_summary(dataset):
    cfg, root, summary = dataset
    episodes = _episodes(root)
    total = sum(len(v) for v in episodes.values())
    assert summary["trajectories"] == total > 0
    assert summary["attempts"] == 6 + 6 + 2  # A* units of both scenes + DAgger units of the train scene
    assert summary["per_split"] == {k: len(v) for k, v in episodes.items() if v}
    assert {e.scene_id for e in episodes[C.SPLIT_TEST_UNSEEN]} <= {"embedded-1"}
    assert {e.scene_id for e in episodes[C.SPLIT_TRAIN] + episodes[C.SPLIT_TEST_SEEN]} <= {"embedded-0"}
    assert summary["vocabulary_size"] > 20 and sum(summary["action_histogram"].values()) > total
    assert json.loads((root / C.TOOLCHAIN_SUMMARY_JSON).read_text()) == summary


def test_the_dataset_records_the_settings_its_readers_need(dataset, tmp_path):
    cfg, root, _ = dataset
    settings = GenerationSettings(width=64, height=64, city_size_m=300.0, city_buildings=30)
    assert read_generation_settings(root) == settings
    older = tmp_path / C.TOOLCHAIN_CONFIG_JSON  # a dataset generated before the record: its config only
    older.parent.mkdir(parents=True)
    shutil.copy(root / C.TOOLCHAIN_CONFIG_JSON, older)
    assert read_generation_settings(tmp_path) == settings


def test_trajectories_replay_without_collision_to_their_goal(dataset):
    cfg, root, _ = dataset
    cities = {}
    for episodes in _episodes(root).values():
        for ep in episodes:
            city = cities.setdefault(
                ep.scene_id, generate_city(parse_scene_id(ep.scene_id), city_config_for(cfg.scenes))
            )
            occupancy = city.occupancy(1.0)
            dagger = ep.episode_id.endswith("_dagger")
            stop = int(np.flatnonzero(ep.actions == C.ACTION_STOP)[0])
            assert np.linalg.norm(ep.positions[stop] - ep.goal) <= C.SUCCESS_RADIUS_M
            assert np.linalg.norm(ep.positions[stop] - ep.goal) <= cfg.planner.goal_tolerance_m
            for t in range(len(ep) - 1):
                pose = Pose(*ep.positions[t], ep.yaws[t])
                assert not occupancy.segment_collides(
                    ep.positions[t], ep.positions[t + 1], ground_z=city.ground_z
                )
                if not dagger:  # A* episodes: the label is the executed motion, exactly
                    nxt = dynamics.apply_action(pose, int(ep.actions[t]))
                    assert (nxt.x, nxt.y, nxt.z, nxt.yaw) == (*ep.positions[t + 1], ep.yaws[t + 1])
            # relabelling merged forwards by displacement changes nothing: labels sit where motion starts
            if not dagger:
                assert ep.category.startswith(("low", "medium", "high"))
                assert ep.pitch_deg == (C.HIGH_CATEGORY_PITCH_DEG if ep.category.startswith("high") else 0.0)


def test_merged_labels_read_the_same_with_start_relabelling(dataset):
    _, root, _ = dataset
    for split in C.SPLITS:
        plain = {e.episode_id: e for e in load_openfly_dataset(root, split, KEEP)}
        relabelled = load_openfly_dataset(
            root, split, ReaderOptions(takeoff_landing="keep", merged_forward_position="start")
        )
        for ep in relabelled:
            if not ep.episode_id.endswith("_dagger"):
                assert ep.actions.tolist() == plain[ep.episode_id].actions.tolist()


def test_boxes_and_frames_match_the_renderer(dataset):
    cfg, root, _ = dataset
    sim = default_simulator(cfg)
    store = FrameStore(root)
    try:
        checked_visible = 0
        for episodes in _episodes(root).values():
            for ep in episodes[:4]:
                frames = store.frames(ep)
                target = ep.landmark_ids[-1]
                for t in range(0, len(ep), 3):
                    obs = sim.render(ep.scene_id, Pose(*ep.positions[t], ep.yaws[t]), ep.pitch_deg)
                    assert np.array_equal(frames[t], obs.rgb)  # PNG round trip is lossless
                    assert bool(ep.box_visible[t]) == (target in (obs.boxes or {}))
                    if ep.box_visible[t]:
                        assert np.allclose(ep.boxes[t], obs.boxes[target], atol=1e-6)
                        checked_visible += 1
        assert checked_visible > 0
    finally:
        sim.close()


def test_instructions_name_the_target_attributes(dataset):
    cfg, root, _ = dataset
    for episodes in _episodes(root).values():
        for ep in episodes:
            city = generate_city(parse_scene_id(ep.scene_id), city_config_for(cfg.scenes))
            target = city.landmark(ep.landmark_ids[-1])
            text = ep.instruction.lower()
            assert target.color in text and target.type in text, (ep.episode_id, text)
            if target.feature != "none":
                assert target.feature in text
            assert ep.instruction[0].isupper() and ep.instruction.endswith(".")


def test_resume_skips_finished_units_and_shards_merge_by_copying(dataset, tmp_path):
    cfg, root, summary = dataset
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    again = generate(dataclasses.replace(cfg, output_dir=str(copy)), progress=False)
    assert again == summary  # nothing left to do: same ledgers, same dataset
    assert len(UnitLedger(copy).read_all()) == summary["attempts"]
    # two shards on two "machines", copied together, summarised
    parts = []
    for i in range(2):
        part = tmp_path / f"shard{i}"
        parts.append(generate(dataclasses.replace(cfg, output_dir=str(part), shard=f"{i}/2"), progress=False))
    merged = tmp_path / "merged"
    for i in range(2):
        shutil.copytree(tmp_path / f"shard{i}", merged, dirs_exist_ok=True)
    from openfly_agent.toolchain.__main__ import main

    assert main(["summarize", f"--root={merged}", "--plots=false"]) == 0
    merged_summary = json.loads((merged / C.TOOLCHAIN_SUMMARY_JSON).read_text())
    assert merged_summary["trajectories"] == summary["trajectories"]
    assert merged_summary["per_split"] == summary["per_split"]
    ids = sorted(e.episode_id for eps in _episodes(merged).values() for e in eps)
    assert ids == sorted(e.episode_id for eps in _episodes(root).values() for e in eps)


def test_spawned_workers_give_the_same_dataset(dataset, tmp_path):
    cfg, root, summary = dataset
    spawned = generate(dataclasses.replace(cfg, output_dir=str(tmp_path / "w2"), workers=2), progress=False)
    assert spawned == summary
    a = {e.episode_id: e for eps in _episodes(root).values() for e in eps}
    b = {e.episode_id: e for eps in _episodes(tmp_path / "w2").values() for e in eps}
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].instruction == b[key].instruction and np.array_equal(a[key].positions, b[key].positions)


def test_an_interrupted_run_resumes_to_the_same_dataset(dataset, tmp_path):
    cfg, root, summary = dataset
    copy = tmp_path / "interrupted"
    shutil.copytree(root, copy)
    ledger = UnitLedger(copy)
    lines = ledger.path("embedded-0").read_text().splitlines()
    ledger.path("embedded-0").write_text("\n".join(lines[:3]) + "\n" + lines[3][:10])  # killed mid-append
    lost = [json.loads(line) for line in lines[3:]]
    for record in lost:  # ... and some of those episodes never reached the disk
        if record["status"] == "ok" and record["index"] % 2:
            (copy / C.DATASET_TRAJ_DIR / f"{record['episode_id']}.parquet").unlink()
    resumed = generate(dataclasses.replace(cfg, output_dir=str(copy)), progress=False)
    assert resumed == summary
    a = {e.episode_id: e for eps in _episodes(root).values() for e in eps}
    b = {e.episode_id: e for eps in _episodes(copy).values() for e in eps}
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].instruction == b[key].instruction and np.array_equal(a[key].boxes, b[key].boxes)


def _file_hashes(root) -> dict[str, str]:
    return {
        str(path.relative_to(root)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(root.rglob("*"))
        if path.is_file()
    }


def test_the_val_split_joins_a_dataset_without_one_and_leaves_its_other_splits_byte_for_byte(
    dataset, tmp_path
):
    cfg, root, summary = dataset
    copy = tmp_path / "older"
    shutil.copytree(root, copy)
    record = json.loads((copy / C.TOOLCHAIN_CONFIG_JSON).read_text())
    for key in ("val_seen_per_scene", "val_seeds", "val_unseen_per_scene"):  # recorded before they existed
        del record["scenes"][key]
    (copy / C.TOOLCHAIN_CONFIG_JSON).write_text(json.dumps(record))
    before = _file_hashes(copy)
    val_scenes = {"val_seen_per_scene": 3, "val_seeds": [5], "val_unseen_per_scene": 4}
    val_cfg = dataclasses.replace(small_config(copy, **val_scenes), dagger=cfg.dagger)
    upgraded = generate(val_cfg, progress=False)

    episodes = _episodes(copy)
    val = episodes[C.SPLIT_VAL]
    assert upgraded["attempts"] == summary["attempts"] + 3 + 4  # only the val units ran
    assert upgraded["per_split"][C.SPLIT_VAL] == len(val) > 0
    # routes of the train city and of the validation city, none of them in another split
    assert {e.scene_id for e in val} == {"embedded-0", "embedded-5"}
    others = [e for split in (C.SPLIT_TRAIN, C.SPLIT_TEST_SEEN, C.SPLIT_TEST_UNSEEN) for e in episodes[split]]
    assert not {e.episode_id for e in others} & {e.episode_id for e in val}
    assert "embedded-5" not in {e.scene_id for e in others}
    # every file of the other splits is the same byte for byte; only the dataset's records and counts change
    after = _file_hashes(copy)
    changed = sorted(name for name, digest in before.items() if after[name] != digest)
    assert changed == sorted(
        [
            "Annotation/val.json",  # was empty
            "meta/data_files.json",
            "meta/info.json",
            "meta/toolchain/generate_config.json",
            "meta/toolchain/summary.json",
            "meta/toolchain/units/embedded-0.jsonl",  # the ledger: the val units' lines appended
        ]
    )


class _StepOnlySimulator:
    """The embedded simulator seen through the bare Simulator protocol (no stateless render())."""

    def __init__(self, cfg):
        self._sim = default_simulator(cfg)

    def reset(self, episode):
        return self._sim.reset(episode)

    def step(self, action_id):
        return self._sim.step(action_id)

    def close(self):
        self._sim.close()


def test_any_simulator_renders_by_stepping_through_the_labels(dataset):
    from openfly_agent.toolchain.pipeline import plan_trajectory, prepare_scene
    from openfly_agent.toolchain.render import render_poses
    from openfly_agent.toolchain.scenes import embedded_scene

    cfg, _, _ = dataset
    cfg = dataclasses.replace(cfg, route=dataclasses.replace(cfg.route, takeoff_landing_prob=0.0))
    prepared = prepare_scene(embedded_scene(0, cfg.scenes), cfg)
    planned = plan_trajectory(prepared, np.random.default_rng(0), cfg)
    direct, stepped = default_simulator(cfg), _StepOnlySimulator(cfg)
    try:
        a = render_poses(direct, "embedded-0", planned.seq.poses, planned.pitch_deg)
        b = render_poses(stepped, "embedded-0", planned.seq.poses, planned.pitch_deg, planned.seq.actions)
    finally:
        direct.close()
        stepped.close()
    assert len(a.frames) == len(b.frames) == len(planned.seq)
    assert all(np.array_equal(x, y) for x, y in zip(a.frames, b.frames))
    assert [sorted(x) for x in a.boxes] == [sorted(y) for y in b.boxes]


def test_policy_dagger_relabels_a_trained_agent_rollout(dataset, tmp_path):
    from openfly_agent.rollout.agent import AgentPolicy
    from openfly_agent.toolchain.pipeline import KIND_DAGGER_POLICY

    class AlwaysLeftAgent:  # stands in for a trained agent's session (predict_step / reset)
        def __init__(self):
            self.frames = 0

        def reset(self, ids):
            pass

        def predict_step(self, observations, true_boxes=None):
            self.frames += sum(o[C.OBS_RGB].shape == (64, 64, 3) for o in observations)
            left = SimpleNamespace(
                action=C.ACTION_TURN_LEFT, box=(0.0,) * 4, box_visible=False, memory_sets=[]
            )
            return [left] * len(observations)

    cfg, _, _ = dataset
    agent = AlwaysLeftAgent()
    out = tmp_path / "policy_dagger"
    summary = generate(
        dataclasses.replace(cfg, output_dir=str(out)), policy=AgentPolicy(agent), kinds=(KIND_DAGGER_POLICY,)
    )
    assert summary["attempts"] == cfg.dagger.episodes_per_scene and agent.frames > 0
    for ep in load_openfly_dataset(out, C.SPLIT_TRAIN, KEEP):
        assert ep.episode_id.endswith("_dagger") and ep.actions[-1] == C.ACTION_STOP
        steps = min(cfg.dagger.max_policy_steps, len(ep) - 1)
        turned = [ep.yaws[t + 1] != ep.yaws[t] for t in range(steps)]
        assert all(turned)  # the agent flew (turned left) ...
        assert (
            ep.actions[0] != C.ACTION_TURN_LEFT or ep.actions[1] != C.ACTION_TURN_LEFT
        )  # ... the expert labels


def test_cli_generate_writes_a_dataset(tmp_path, capsys):
    from openfly_agent.toolchain.__main__ import main
    from openfly_agent.utils.config import config_to_dict

    cfg = small_config(tmp_path / "cli", trajectories_per_scene=2)
    cfg = dataclasses.replace(cfg, dagger=DaggerConfig(episodes_per_scene=0))
    config = tmp_path / "tiny.yaml"
    import yaml

    config.write_text(yaml.safe_dump(config_to_dict(cfg)))
    main(["generate", "--config_path", str(config), "--shard=0/1"])
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["trajectories"] == sum(printed["per_split"].values()) > 0
    assert (tmp_path / "cli" / C.DATASET_INFO_JSON).is_file()


def test_a_rerun_with_other_settings_is_refused_unless_overwrite(dataset, tmp_path, capsys):
    import yaml

    from openfly_agent.toolchain.__main__ import main
    from openfly_agent.toolchain.settings import GenerateSettingsError
    from openfly_agent.utils.config import config_to_dict

    cfg, root, summary = dataset
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    bigger = dataclasses.replace(cfg, output_dir=str(copy), render=RenderConfig(width=96, height=96))
    with pytest.raises(GenerateSettingsError, match=r"render\.height: 64 -> 96; render\.width: 64 -> 96"):
        generate(bigger, progress=False)
    assert json.loads((copy / C.TOOLCHAIN_CONFIG_JSON).read_text())["render"]["width"] == 64  # record kept
    # The command line says the same in one line, exit code 2.
    config = tmp_path / "small.yaml"
    config.write_text(yaml.safe_dump(config_to_dict(dataclasses.replace(cfg, output_dir=str(copy)))))
    assert main(["generate", "--config_path", str(config), "--render.width=96", "--render.height=96"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "render.width: 64 -> 96" in err[0] and "--overwrite=true" in err[0]
    # Settings that do not change the data (workers, plots, shard) still resume, to the same dataset.
    assert (
        generate(dataclasses.replace(cfg, output_dir=str(copy), workers=1, plots=False), progress=False)
        == summary
    )
    # --overwrite discards the old dataset: only 96 px trajectories remain.
    fresh = dataclasses.replace(
        bigger, overwrite=True, scenes=dataclasses.replace(cfg.scenes, trajectories_per_scene=2),
        dagger=DaggerConfig(episodes_per_scene=0),
    )  # fmt: skip
    generate(fresh, progress=False)
    episodes = [e for eps in _episodes(copy).values() for e in eps]
    assert episodes and len(episodes) < summary["trajectories"]
    assert all(FrameStore(copy).frame(e, 0).shape == (96, 96, 3) for e in episodes)
    assert json.loads((copy / C.TOOLCHAIN_CONFIG_JSON).read_text())["render"]["width"] == 96


def _failing_simulator(cfg):
    raise RuntimeError("no renderer on this machine")


def test_a_first_run_that_fails_leaves_no_settings_record(tmp_path):
    """The failed run's generate_config.json would make the corrected command refuse the folder as "a dataset
    generated with other settings": it goes, with the folders the run made; files that were there stay."""
    cfg = small_config(tmp_path / "outputs" / "data", trajectories_per_scene=1)
    with pytest.raises(RuntimeError, match="no renderer"):
        generate(cfg, sim_factory=_failing_simulator, progress=False)
    assert list(tmp_path.iterdir()) == []
    kept = tmp_path / "mine"
    kept.mkdir()
    (kept / "notes.txt").write_text("mine\n")
    with pytest.raises(RuntimeError, match="no renderer"):
        generate(
            dataclasses.replace(cfg, output_dir=str(kept)), sim_factory=_failing_simulator, progress=False
        )
    assert [path.name for path in kept.rglob("*")] == ["notes.txt"]


def test_a_run_that_wrote_episodes_keeps_its_record_to_resume(tmp_path):
    from openfly_agent.toolchain.settings import record_kept_on_success

    root = tmp_path / "data"
    with pytest.raises(KeyboardInterrupt), record_kept_on_success(root):
        (root / C.TOOLCHAIN_CONFIG_JSON).parent.mkdir(parents=True)
        (root / C.TOOLCHAIN_CONFIG_JSON).write_text("{}\n")
        (root / C.DATASET_TRAJ_DIR).mkdir()
        (root / C.DATASET_TRAJ_DIR / "episode.parquet").write_bytes(b"written")
        raise KeyboardInterrupt  # Ctrl-C after the first episode: the same command resumes
    assert (root / C.TOOLCHAIN_CONFIG_JSON).read_text() == "{}\n"


def test_empty_splits_are_named_with_the_settings_that_fill_them():
    from openfly_agent.toolchain.summary import empty_splits_message

    assert empty_splits_message({"per_split": {"train": 5, "test_seen": 1, "test_unseen": 2}}) is None
    message = empty_splits_message({"per_split": {"train": 5, "test_unseen": 2}})
    assert message.startswith("split(s) test_seen came out empty (0 trajectories)")
    assert "--scenes.test_seen_fraction" in message and "unseen_seeds" not in message


def test_cli_generate_warns_after_its_summary_when_a_split_came_out_empty(monkeypatch, tmp_path, capsys):
    from openfly_agent.toolchain import __main__ as cli

    summary = {"trajectories": 3, "per_split": {"train": 3}, "rejected": {}, "vocabulary_size": 9}
    monkeypatch.setattr(cli, "generate", lambda cfg: summary)
    assert cli.main(["generate", f"--output_dir={tmp_path / 'data'}"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out) == summary
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "python -m openfly_agent.toolchain generate: warning: split(s) test_seen, test_unseen came out empty"
    )


def test_default_route_options_give_the_routes_and_instructions_pinned_before_chain_landmarks(tmp_path):
    """The data of today's configs is unchanged by `route.chain_landmarks` / `instructions.name_every_target` /
    `instructions.name_passed_landmark` at their defaults: the digest below was computed with the code before
    they existed (commit c795c3e)."""
    cfg = small_config(tmp_path, trajectories_per_scene=8)
    cfg.route.chain_prob, cfg.dagger.episodes_per_scene = 0.5, 0
    generate(cfg, progress=False)
    episodes = sorted(
        (
            e
            for f in ("train", "seen", "unseen")
            for e in json.loads((tmp_path / "Annotation" / f"{f}.json").read_text())
        ),
        key=lambda e: e["image_path"],
    )
    digest = hashlib.sha256()
    for e in episodes:
        pos = ";".join(",".join(f"{v:.6f}" for v in p) for p in e["pos"])
        yaw = ",".join(f"{v:.6f}" for v in e["yaw"])
        fields = [e["image_path"], e["gpt_instruction"], str(e["action"]), str(e["landmark_ids"]), pos, yaw]
        digest.update("|".join(fields).encode())
    assert len(episodes) == 16 and sum(len(e["landmark_ids"]) == 2 for e in episodes) == 6
    assert digest.hexdigest() == "de630c311b9e25bb465cb167cbcd7b026f38bc64c397a3b96acd82c8fa7062a6"


def test_a_dataset_recorded_before_an_option_existed_resumes_at_its_default(dataset, tmp_path):
    from openfly_agent.toolchain.settings import GenerateSettingsError

    cfg, root, summary = dataset
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    record = copy / C.TOOLCHAIN_CONFIG_JSON
    stored = json.loads(record.read_text())
    del stored["route"]["chain_landmarks"], stored["instructions"]["name_every_target"]
    del stored["instructions"]["name_passed_landmark"]
    record.write_text(json.dumps(stored))
    assert generate(dataclasses.replace(cfg, output_dir=str(copy)), progress=False) == summary
    longer = dataclasses.replace(
        cfg, output_dir=str(copy), route=dataclasses.replace(cfg.route, chain_landmarks=[3, 4])
    )
    with pytest.raises(GenerateSettingsError, match=r"route\.chain_landmarks: \[2, 2\] -> \[3, 4\]"):
        generate(longer, progress=False)
