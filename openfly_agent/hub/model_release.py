"""Model release: a run checkpoint -> a Hub-ready folder (weights, config with auto_map, tokenizer, card)."""

from __future__ import annotations

import fnmatch
import logging
import re
import shutil
from pathlib import Path

from openfly_agent import __version__
from openfly_agent.constants import (
    ACTION_TOKENIZER_NAME,
    ADAPTER_DIR_NAME,
    CONFIG_NAME,
    MODEL_CARD_NAME,
    MODEL_TYPE,
    NORM_STATS_NAME,
    PROCESSOR_CONFIG_NAME,
    TRAIN_CONFIG_NAME,
    TRAINER_STATE_NAME,
    WEIGHTS_INDEX_NAME,
    WEIGHTS_NAME,
)
from openfly_agent.hub.config import ModelReleaseConfig
from openfly_agent.hub.folder_utils import DEFAULT_RELEASE_ROOT, prepare_output_dir, read_json
from openfly_agent.hub.model_card import (
    ModelFacts,
    describe_architecture,
    describe_lora,
    describe_training_progress,
    render_model_card,
    summarize_train_config,
)
from openfly_agent.hub.results import load_results, resolve_results_path
from openfly_agent.hub.results_source import check_results_weights, load_baselines
from openfly_agent.model.persistence.checkpoint_path import (
    check_navigation_stage,
    check_weights_readable,
    resolve_checkpoint_folder,
)
from openfly_agent.model.persistence.lora_checkpoint import (
    base_of,
    checkpoint_weights,
    is_lora_checkpoint,
    load_lora_agent,
)
from openfly_agent.model.persistence.remote_code import CONFIGURATION_FILE, MODELING_FILE, PROCESSING_FILE
from openfly_agent.utils.file_modes import follow_umask

logger = logging.getLogger(__name__)

EVAL_RESULTS_NAME = "eval_results.json"
# Files of a checkpoint the release carries over when the agent's own save did not write them (a LoRA run's
# merged model has no run records: they come from the checkpoint it merged).
CARRIED_FILES = (TRAIN_CONFIG_NAME, TRAINER_STATE_NAME, NORM_STATS_NAME, ACTION_TOKENIZER_NAME)
# A backticked name in the card that looks like a file or folder of the release (`check_card_files`) ...
CARD_FILE_NAME = re.compile(r"`([\w.-]+(?:\.(?:json|jsonl|safetensors|py|md|txt)|/))`")
# ... except the code repository's scripts the card tells readers to run.
REPOSITORY_SCRIPTS = ("eval.py", "train.py")
# Pickle-based formats never enter a release (security: weights are safetensors only).
FORBIDDEN_SUFFIXES = (".bin", ".pt", ".pth", ".pkl", ".ckpt")


def resolve_checkpoint(path: str | Path) -> Path:
    """The checkpoint folder: `path` itself, or the folder named by a training `last` pointer file.

    Accepts a checkpoint folder (holding config.json), the pointer file `.../checkpoints/last`, or a folder
    holding such a pointer (`<run>/checkpoints` or `<run>`). A grounding-stage checkpoint is refused (no
    trained action head).
    """
    folder = resolve_checkpoint_folder(path)
    if folder is None:
        raise FileNotFoundError(
            f"{path} is not a checkpoint folder (no {CONFIG_NAME}): pass e.g. <run>/checkpoints/step-000100 "
            "or the <run>/checkpoints/last pointer"
        )
    model_type = read_json(folder / CONFIG_NAME).get("model_type")
    if model_type != MODEL_TYPE:
        raise ValueError(f"{folder / CONFIG_NAME}: model_type is {model_type!r}, expected {MODEL_TYPE!r}")
    check_navigation_stage(folder)
    return folder


def build_model_release(cfg: ModelReleaseConfig) -> Path:
    """Write the release folder for `cfg.checkpoint` and return it.

    Full checkpoints are loaded and saved again with `max_shard_size`. LoRA checkpoints (metadata +
    `adapter/`) are released merged (`cfg.lora`): the run's merged model when it wrote one, else the adapter
    rebuilt on its base weights and merged (`checkpoint_weights`, logged); or as the adapter alone.
    The agent's own save writes the processor files and the `trust_remote_code` modules with `auto_map` (an
    adapter release has neither: no weights to load). Then: training config / norm stats carried over, the eval
    results, README.md. Inputs are checked first.
    """
    checkpoint = resolve_checkpoint(cfg.checkpoint)
    source = checkpoint  # the run's checkpoint; `checkpoint` becomes the folder whose weights are released
    check_weights_readable(checkpoint)  # a truncated copy: one line, before the release folder is made
    results = load_results(cfg.results) if cfg.results else None
    baselines = []
    if results is not None:
        results_file = resolve_results_path(cfg.results)
        check_results_weights(results_file, checkpoint)
        baselines = load_baselines(results_file, results)
    adapter_form = is_lora_checkpoint(checkpoint) and cfg.lora == "adapter"
    if adapter_form:
        base = base_of(checkpoint, cfg.base_checkpoint)
    else:
        weights = checkpoint_weights(checkpoint, cfg.base_checkpoint)
        logger.info("releasing %s", weights.description)
        checkpoint, base = weights.folder, weights.base
    if adapter_form and not cfg.card.base_model:
        raise ValueError("--lora adapter needs --card.base_model=<Hub id of the base weights> for the card")
    out = prepare_output_dir(
        cfg.output_dir or DEFAULT_RELEASE_ROOT / cfg.repo_id.split("/", 1)[1], cfg.overwrite
    )
    logger.info("releasing %s -> %s", checkpoint, out)
    lora = is_lora_checkpoint(source)
    agent, form = _write_weights(checkpoint, base, adapter_form, out, cfg.max_shard_size, lora)
    for file_name in CARRIED_FILES:
        origin = next((f / file_name for f in (checkpoint, source) if (f / file_name).is_file()), None)
        if origin is not None and not (out / file_name).exists():
            shutil.copy2(origin, out / file_name)
    if results is not None:
        shutil.copy2(resolve_results_path(cfg.results), out / EVAL_RESULTS_NAME)
    facts = model_facts(agent, out, release_form=form, adapter_release=adapter_form)
    train_config = read_json(out / TRAIN_CONFIG_NAME) if (out / TRAIN_CONFIG_NAME).is_file() else None
    trainer_state = read_json(out / TRAINER_STATE_NAME) if (out / TRAINER_STATE_NAME).is_file() else None
    if train_config is not None:
        facts.train_summary = summarize_train_config(train_config)
    facts.training_progress = describe_training_progress(train_config, trainer_state)
    if lora:
        adapter_config = read_json(source / ADAPTER_DIR_NAME / "adapter_config.json")
        init = ((train_config or {}).get("init") or {}).get("checkpoint")
        facts.lora_summary = describe_lora(
            adapter_config, base or init, train_config, trainer_state, not adapter_form
        )
    card = render_model_card(cfg.card, cfg.repo_id, results, facts, baselines)
    (out / MODEL_CARD_NAME).write_text(card)
    check_release_folder(out, adapter_form)
    follow_umask(out)  # safetensors writes 0600; the weights take the mode of the files beside them
    logger.info("release folder ready: %s (%d files)", out, len(list(out.iterdir())))
    return out


def _write_weights(
    checkpoint: Path, base: str | None, adapter_form: bool, out: Path, max_shard_size: str, lora: bool
):
    """Save the weights into `out` in the chosen form; returns (agent, description of the form).

    `lora`: the release is of a LoRA run, whose merged model (`checkpoint`, no `base`) is released as is.
    """
    from openfly_agent.model.agent import OpenFlyAgent  # lazy: torch + transformers
    from openfly_agent.model.language.lora import merge_lora, save_lora_adapter  # lazy: torch
    from openfly_agent.training.export import write_model_metadata  # lazy: torch + accelerate

    if base is None:
        agent = OpenFlyAgent.from_pretrained(str(checkpoint)).eval()
        agent.save_pretrained(out, max_shard_size=max_shard_size)
        if lora:
            return agent, "LoRA adapter merged into its base weights at the end of the run (full weights)"
        return agent, "full weights"
    agent = load_lora_agent(checkpoint, base)  # also proves the adapter fits its base
    if adapter_form:
        write_model_metadata(agent, out)  # config, tokenizer, action tokenizer, norm stats: no weights
        adapter = save_lora_adapter(agent, out)
        # peft writes an empty card template beside the adapter; the release's card is the root README.md
        (adapter / MODEL_CARD_NAME).unlink(missing_ok=True)
        return agent, "LoRA adapter only (`adapter/`); load it on its base weights (see Usage)"
    merge_lora(agent)
    agent.save_pretrained(out, max_shard_size=max_shard_size)
    return agent, f"LoRA adapter merged into its base weights (`{Path(base).name}`)"


def model_facts(agent, folder: Path, release_form: str, adapter_release: bool = False) -> ModelFacts:
    """What the card says about the weights in `folder`."""
    cfg = agent.model_cfg
    num_params = sum(p.numel() for p in agent.parameters())
    return ModelFacts(
        package_version=__version__,
        num_parameters=_human_count(num_params),
        action_head=cfg.action_head.type,
        architecture=describe_architecture(cfg),
        weights_summary=_weights_summary(folder),
        release_form=release_form,
        files=describe_files(folder),
        adapter_release=adapter_release,
    )


def describe_files(folder: Path) -> dict[str, str]:
    """A one-line description of every file of the release (README.md included)."""
    known = {
        CONFIG_NAME: "model config (`model_type: openfly_agent`, model sections, norm stats, `auto_map`)",
        WEIGHTS_NAME: "weights (safetensors)",
        WEIGHTS_INDEX_NAME: "tensor name -> shard file",
        ACTION_TOKENIZER_NAME: "action head settings: action ids <-> token ids / bins",
        NORM_STATS_NAME: "action normalisation statistics (OpenVLA `dataset_statistics` format)",
        TRAIN_CONFIG_NAME: "the training configuration used",
        TRAINER_STATE_NAME: "the checkpoint's training counters (optimizer steps, epoch, samples seen)",
        EVAL_RESULTS_NAME: "the eval.py results the card's numbers come from",
        PROCESSOR_CONFIG_NAME: "input processor: image size, prompt template, text limit, action head, norm stats",
        CONFIGURATION_FILE: "`trust_remote_code` entry: imports the config class of `openfly-agent`",
        MODELING_FILE: "`trust_remote_code` entry: imports the model class of `openfly-agent`",
        PROCESSING_FILE: "`trust_remote_code` entry: imports the processor class of `openfly-agent`",
        "tokenizer.json": "text tokenizer",
        "tokenizer_config.json": "text tokenizer settings",
        "special_tokens_map.json": "text tokenizer special tokens",
        MODEL_CARD_NAME: "this card",
    }
    names = sorted({p.name for p in folder.iterdir() if p.is_file()} | {MODEL_CARD_NAME})
    shards = [n for n in names if n.startswith("model-") and n.endswith(".safetensors")]
    described = {n: known.get(n, "") for n in names if n not in shards}
    if (folder / ADAPTER_DIR_NAME).is_dir():
        described[f"{ADAPTER_DIR_NAME}/"] = "LoRA adapter: peft files of the LLM + projector / grounding head"
    if shards:
        described[f"model-000NN-of-{len(shards):05d}.safetensors"] = (
            f"weights, {len(shards)} safetensors shards"
        )
    return described


def check_release_folder(folder: Path, adapter_form: bool = False) -> None:
    """Fail if a pickle-based weight file slipped in, a full release's config.json lacks `auto_map`, or the
    card names a file the folder does not hold (`check_card_files`)."""
    bad = sorted(p.name for p in folder.rglob("*") if p.suffix in FORBIDDEN_SUFFIXES)
    if bad:
        raise ValueError(f"{folder}: pickle-based files must not be released (safetensors only): {bad}")
    if not adapter_form and "auto_map" not in read_json(folder / CONFIG_NAME):
        raise ValueError(f"{folder / CONFIG_NAME}: auto_map is missing")
    check_card_files(folder)


def check_card_files(folder: Path) -> None:
    """Fail if the card (README.md) names, in backticks, a file or folder of the release that `folder` lacks.

    A name looks like one of the release's when it is a bare file name with a suffix a release holds (`.json`,
    `.safetensors`, `.py`, ...) or a folder name ending in `/`; the shard pattern `model-000NN-of-...` stands for
    its shards; the repository's own scripts (`eval.py`) are commands, not files of the release.
    """
    card = (folder / MODEL_CARD_NAME).read_text()
    missing = []
    for name in sorted(set(CARD_FILE_NAME.findall(card)) - set(REPOSITORY_SCRIPTS)):
        if name.endswith("/"):
            found = (folder / name).is_dir()
        else:
            found = bool(fnmatch.filter((p.name for p in folder.iterdir()), name.replace("NN", "[0-9][0-9]")))
        if not found:
            missing.append(name)
    if missing:
        raise ValueError(f"{folder / MODEL_CARD_NAME} names files the release does not hold: {missing}")


def _weights_summary(folder: Path) -> str:
    if not list(folder.glob("*.safetensors")) and (folder / ADAPTER_DIR_NAME).is_dir():
        size = sum(p.stat().st_size for p in (folder / ADAPTER_DIR_NAME).glob("*.safetensors"))
        return f"LoRA adapter in `{ADAPTER_DIR_NAME}/`, {_human_bytes(size)}"
    files = sorted(folder.glob("*.safetensors"))
    size = sum(p.stat().st_size for p in files)
    if (folder / WEIGHTS_INDEX_NAME).is_file():
        return f"{len(files)} safetensors shards + `{WEIGHTS_INDEX_NAME}`, {_human_bytes(size)}"
    return f"`{WEIGHTS_NAME}`, {_human_bytes(size)}"


def _human_count(n: int) -> str:
    for unit, scale in (("B", 1e9), ("M", 1e6), ("K", 1e3)):
        if n >= scale:
            return f"{n / scale:.2f} {unit}"
    return str(n)


def _human_bytes(n: int) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"
