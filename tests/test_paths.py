"""One rule for relative paths (docs/USAGE.md, "Where files go"): outputs and datasets are relative to the working
directory; config files not found there are read from the repository's configs/, so every command works from
any folder and writes where it is run."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from openfly_agent.utils.config import REPO_ROOT, resolve_config_path

REPO = Path(__file__).resolve().parents[1]


def _train_module():
    spec = importlib.util.spec_from_file_location("train_entry_point", REPO / "train.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_config_paths_fall_back_to_the_repository(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    shipped = "configs/toolchain/embedded-small.yaml"
    assert REPO_ROOT == REPO
    assert resolve_config_path(shipped) == REPO / shipped
    local = tmp_path / shipped  # a file of the same name in the working directory wins
    local.parent.mkdir(parents=True)
    local.write_text("seed: 3\n")
    assert resolve_config_path(shipped) == Path(shipped)
    assert resolve_config_path("nowhere.yaml") == Path("nowhere.yaml")  # errors name the path as given


def test_train_from_another_folder_reads_repo_configs_and_writes_here(tmp_path, monkeypatch):
    """The default run from elsewhere: a plain `toolchain generate` reads its config from the repository and
    writes the dataset train.py reads under ./outputs of the working directory, where the run folder goes too."""
    from openfly_agent.toolchain.__main__ import _parse_generate

    monkeypatch.chdir(tmp_path)
    train = _train_module()
    cfg = train.parse_args([])
    assert Path(cfg.output_dir).resolve() == tmp_path / "outputs" / "train" / "tiny"
    generate_cfg = _parse_generate([])  # `python -m openfly_agent.toolchain generate`
    assert Path(generate_cfg.output_dir).resolve() == Path(cfg.data.root).resolve()
    assert Path(cfg.data.root).resolve() == tmp_path / "outputs" / "datasets" / "embedded-small"
    assert generate_cfg.scenes.trajectories_per_scene == 130  # the repository's embedded-small.yaml
    from openfly_agent.eval.config import EvalConfig

    # eval reads the dataset and writes results where train and generate put them
    assert EvalConfig(policy="stop").dataset_root == cfg.data.root == generate_cfg.output_dir
