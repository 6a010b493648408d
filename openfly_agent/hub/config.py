"""Typed settings of the release commands (model and dataset); validation only, no I/O."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

# Hub repo ids: "namespace/name" of letters, digits, '-', '_', '.'; no '--' or '..', no trailing '-' or '.'.
_REPO_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,95}/[A-Za-z0-9][A-Za-z0-9_.-]{0,95}$")
LORA_MODES = ("merged", "adapter")
DEFAULT_MAX_SHARD_SIZE = "5GB"
_SIZE = re.compile(r"^\d+(\.\d+)?\s*(B|KB|MB|GB|TB|KIB|MIB|GIB|TIB)$", re.IGNORECASE)


def check_repo_id(repo_id: str, flag: str = "--repo_id") -> None:
    """Raise a ValueError naming `flag` unless `repo_id` looks like `namespace/name`."""
    if not _REPO_ID.match(repo_id) or "--" in repo_id or ".." in repo_id or repo_id.endswith((".", "-")):
        raise ValueError(
            f"{flag} {repo_id!r} is not a Hub repo id: write it as 'namespace/name' "
            "(letters, digits, '-', '_', '.'; e.g. 'my-user/openfly-agent-tiny')"
        )


def check_revision(revision: str | None) -> None:
    """Raise a ValueError unless `revision` is None or a plain branch name."""
    if revision is not None and (not revision.strip() or revision.startswith(("-", "/")) or " " in revision):
        raise ValueError(f"--revision {revision!r} is not a branch name: use e.g. 'main' or 'v0.1'")


@dataclass
class CardConfig:
    """Metadata of the model card (YAML front matter). Defaults describe the tiny embedded release."""

    license: str = (
        "mit"  # Hub licence id (e.g. `mit`); `other` needs `license_name` and `license_link` (Llama 2)
    )
    license_name: str | None = None  # name of a custom licence (only with `license: other`)
    license_link: str | None = (
        None  # URL or in-repo path of the custom licence text (only with `license: other`)
    )
    base_model: str | None = (
        None  # Hub id the weights were fine-tuned from (`openvla/openvla-7b`); None: scratch
    )
    datasets: list[str] = field(default_factory=list)  # Hub dataset ids the model was trained / evaluated on
    eval_dataset: str = (
        "openfly-embedded"  # Hub dataset id (or name) the card's `model-index` results refer to
    )
    eval_dataset_name: str = "OpenFly embedded city"  # human name of that dataset, shown next to each result
    tags: list[str] = field(default_factory=list)  # extra tags; the fixed OpenFly tags are always added
    language: list[str] = field(default_factory=lambda: ["en"])  # languages of the instructions
    pipeline_tag: str = "robotics"  # Hub task of the model
    # Git URL of the `openfly-agent` source the card's install line clones; None: the card says to install the
    # package from a clone (it is not published on PyPI)
    code_url: str | None = None

    def __post_init__(self) -> None:
        if not self.license:
            raise ValueError(
                "card.license is empty: set an id such as 'mit' or 'other' (+ license_name/link)"
            )
        if self.license == "other" and not (self.license_name and self.license_link):
            raise ValueError("card.license 'other' needs card.license_name and card.license_link")
        if self.base_model is not None:
            check_repo_id(self.base_model, flag="--card.base_model")
        if not self.eval_dataset:
            raise ValueError("card.eval_dataset is empty: name the dataset the results were measured on")


@dataclass
class ModelReleaseConfig:
    """`python -m openfly_agent.hub release`: checkpoint folder -> release folder (-> Hub model repo)."""

    checkpoint: str = (
        ""  # run checkpoint folder (config.json + safetensors + tokenizer + action tokenizer ...)
    )
    repo_id: str = ""  # target Hub repo, `namespace/name`; also used in the card's usage code
    output_dir: str | None = None  # release folder to write; default `outputs/releases/<name>`
    results: str | None = None  # eval results JSON (eval.py's `results.json`) for the card's `model-index`
    lora: str = (
        "merged"  # LoRA checkpoints: `merged` (full weights) or `adapter` (adapter weights + base reference)
    )
    # base weights of a LoRA checkpoint (folder or Hub id, ours or OpenVLA); default the `init.checkpoint`
    # recorded in its train_config.json
    base_checkpoint: str | None = None
    # weights above this size are split into shards + index (transformers notation, "5GB")
    max_shard_size: str = DEFAULT_MAX_SHARD_SIZE
    push: bool = False  # upload the folder after writing it
    private: bool = False  # create the repo private (only when it does not exist yet)
    revision: str | None = None  # branch to push to (created from main when missing); default main
    commit_message: str = "Release OpenFly-Agent checkpoint"  # commit message of the upload
    overwrite: bool = False  # replace an existing, non-empty output folder
    card: CardConfig = field(default_factory=CardConfig)  # card metadata

    def __post_init__(self) -> None:
        if not self.checkpoint:
            raise ValueError("--checkpoint is required: the run checkpoint folder to release")
        check_repo_id(self.repo_id)
        check_revision(self.revision)
        if self.lora not in LORA_MODES:
            raise ValueError(f"--lora {self.lora!r}: choose one of {LORA_MODES}")
        if not _SIZE.match(self.max_shard_size.strip()):
            raise ValueError(
                f"--max_shard_size {self.max_shard_size!r}: write a size such as '5GB' or '200MB'"
            )


@dataclass
class DatasetReleaseConfig:
    """`python -m openfly_agent.hub release-dataset`: dataset root -> release folder (-> Hub dataset repo)."""

    dataset_root: str = ""  # generated dataset root (traj/**.parquet, Annotation/*.json, meta/info.json)
    repo_id: str = ""  # target Hub dataset repo, `namespace/name`
    card: str = "data_cards/embedded.md"  # card template (Markdown with YAML front matter)
    output_dir: str | None = None  # release folder to write; default `outputs/releases/<name>`
    push: bool = False  # upload the folder after writing it
    private: bool = False  # create the repo private (only when it does not exist yet)
    revision: str | None = None  # branch to push to; default main
    commit_message: str = "Release OpenFly dataset"  # commit message of the upload
    overwrite: bool = False  # replace an existing, non-empty output folder

    def __post_init__(self) -> None:
        if not self.dataset_root:
            raise ValueError("--dataset_root is required: the generated dataset folder to release")
        check_repo_id(self.repo_id)
        check_revision(self.revision)
        if not self.card:
            raise ValueError("--card is required: the dataset card template, e.g. data_cards/embedded.md")


@dataclass
class FakeHubConfig:
    """`python -m openfly_agent.hub fake-hub`: a loopback stand-in for the Hub upload API (rehearsal)."""

    token: str = ""  # the token clients must send (use the value of HF_TOKEN)

    def __post_init__(self) -> None:
        if not self.token:
            raise ValueError("--token is required: the token clients must send (use the value of HF_TOKEN)")
