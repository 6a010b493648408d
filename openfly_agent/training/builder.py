"""Build an OpenFly-Agent training run from a `TrainConfig`: preflight, tokenizer, agent, datasets, collator.

Every check that can fail on user input runs before the model is built (training/preflight.py).
"""

from __future__ import annotations

import collections
import json
import logging
from pathlib import Path

import torch
from accelerate import Accelerator
from accelerate.utils import set_seed

from openfly_agent import constants as C
from openfly_agent.data.collator import NavigationCollator
from openfly_agent.data.dataset import NavigationStepDataset
from openfly_agent.data.frames import FrameStore
from openfly_agent.data.stats import compute_action_statistics
from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.model.config import HEAD_OPENVLA_BINS, LLM_TINY, ModelConfig
from openfly_agent.model.openvla_loader import agent_from_openvla_checkpoint
from openfly_agent.model.tokenizer import load_tokenizer, train_bpe_tokenizer
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.engine import assemble_run, make_accelerator
from openfly_agent.training.export import export_merged_lora, make_exporter
from openfly_agent.training.loop import TrainingRun
from openfly_agent.training.modes import apply_training_mode
from openfly_agent.training.preflight import (
    PreflightError,
    check_dataset_root,
    check_frames_readable,
    check_output_dir,
    checkpoint_tensor_shapes,
    compare_shapes,
    diff_configs,
    load_split,
)
from openfly_agent.utils.config import save_config

logger = logging.getLogger(__name__)

TOKENIZER_DIR = "tokenizer"
FORMAT_OURS, FORMAT_OPENVLA = "openfly", "openvla"


def build_run(cfg: TrainConfig) -> TrainingRun:
    """Check everything, then build the agent, data and loaders of `cfg` and return the ready run."""
    resume_from = check_output_dir(cfg.output_dir, cfg.resume)
    check_dataset_root(cfg.data)
    accelerator = make_accelerator(cfg)
    if accelerator.is_main_process:
        CheckpointManager(cfg.output_dir, cfg.checkpoint.keep_last).remove_stale_staging()
    splits = dict.fromkeys((cfg.data.train_split, cfg.data.val_split, cfg.data.test_split))
    episodes = {split: load_split(cfg.data, split) for split in splits}
    frames = FrameStore(
        cfg.data.root, cache_episodes=cfg.data.cache_episodes, cache_frames=cfg.data.cache_frames
    )
    check_frames_readable(frames, episodes[cfg.data.train_split])
    tokenizer = resolve_tokenizer(cfg, episodes[cfg.data.train_split], accelerator)
    norm_stats = None
    if cfg.model.action_head.type == HEAD_OPENVLA_BINS:
        norm_stats = {Path(cfg.data.root).name: compute_action_statistics(episodes[cfg.data.train_split])}
    init_format = check_init_checkpoint(cfg, tokenizer, norm_stats)
    if resume_from is not None:
        check_architecture(cfg.model, tokenizer, norm_stats, resume_from, "the checkpoint to resume")
    set_seed(cfg.seed)  # the same initial weights on every process and on resume
    agent = build_agent(cfg, tokenizer, norm_stats, init_format)
    apply_training_mode(agent, cfg)
    datasets = {split: make_dataset(cfg, agent, episodes[split], frames) for split in splits}
    collator = make_collator(agent, cfg)
    if accelerator.is_main_process:
        save_config(cfg, Path(cfg.output_dir) / C.TRAIN_CONFIG_NAME)
    test = datasets[cfg.data.test_split]
    return assemble_run(
        cfg,
        accelerator,
        agent,
        datasets[cfg.data.train_split],
        collator,
        make_export=lambda prepared: make_exporter(accelerator, prepared, cfg),
        val_dataset=datasets[cfg.data.val_split],
        test_dataset=test,
        resume_from=resume_from,
        majority_rate=lambda indices: majority_class_rate(datasets[cfg.data.train_split], test, indices),
        after_training=merge_lora_at_end if cfg.use_lora and cfg.lora.merge_at_end else None,
    )


def merge_lora_at_end(run: TrainingRun) -> None:
    """The `lora.merge_at_end` step: full merged weights in `<output_dir>/merged` (rank 0, CPU)."""
    export_merged_lora(run.accelerator, run.model, run.cfg.output_dir)


def make_dataset(
    cfg: TrainConfig, agent: OpenFlyAgent, episodes: list, frames: FrameStore
) -> NavigationStepDataset:
    """Per-step samples of `episodes` with the history mode of `cfg` and the agent's keyframe selector."""
    return NavigationStepDataset(
        episodes,
        frames,
        keyframe_selector=agent.keyframe_selector,
        history=cfg.data.history.mode,
        capacity=cfg.model.memory.capacity,
        set_size=cfg.model.keyframes.set_size,
        seed=cfg.seed,
    )


def make_collator(agent: OpenFlyAgent, cfg: TrainConfig) -> NavigationCollator:
    """The collator around the agent's processor (which prepares text, action targets and frames)."""
    return NavigationCollator(agent.processor, cfg.model.memory.capacity, cfg.model.keyframes.set_size)


def resolve_tokenizer(cfg: TrainConfig, train_episodes: list, accelerator: Accelerator):
    """The run's tokenizer (order in `TokenizerConfig`); a trained one is written by rank 0 first."""
    candidates = [cfg.tokenizer.path, cfg.model.llm.tokenizer_path]
    if cfg.init.checkpoint and (Path(cfg.init.checkpoint) / "tokenizer_config.json").is_file():
        candidates.append(cfg.init.checkpoint)
    own = Path(cfg.output_dir) / TOKENIZER_DIR
    for folder in [c for c in candidates if c]:
        logger.info("tokenizer: %s", folder)
        return load_tokenizer(folder)
    if cfg.model.llm.preset != LLM_TINY and not (own / "tokenizer_config.json").is_file():
        raise PreflightError(
            f"llm.preset={cfg.model.llm.preset} needs its tokenizer: set --tokenizer.path or "
            "--model.llm.tokenizer_path to a local folder (nothing is downloaded)"
        )
    with accelerator.main_process_first():
        if not (own / "tokenizer_config.json").is_file():
            texts = sorted({e.instruction for e in train_episodes})
            logger.info(
                "training a BPE tokenizer (%d tokens) on %d instructions -> %s",
                cfg.tokenizer.train_vocab_size,
                len(texts),
                own,
            )
            return train_bpe_tokenizer(texts, cfg.tokenizer.train_vocab_size, out_dir=own)
        return load_tokenizer(own)


def detect_init_format(folder: Path, requested: str) -> str:
    """`openfly` when config.json carries our model_type, else `openvla` (or what the config asks)."""
    if requested != "auto":
        return requested
    config = folder / C.CONFIG_NAME
    if not config.is_file():
        raise PreflightError(
            f"init.checkpoint {folder} has no {C.CONFIG_NAME}: not a Hugging Face model folder"
        )
    model_type = json.loads(config.read_text()).get("model_type")
    return FORMAT_OURS if model_type == C.MODEL_TYPE else FORMAT_OPENVLA


def check_init_checkpoint(cfg: TrainConfig, tokenizer, norm_stats: dict | None) -> str | None:
    """Validate `init.checkpoint` against the model config before any weight is read; return its format."""
    if cfg.init.checkpoint is None:
        return None
    folder = Path(cfg.init.checkpoint)
    if not folder.is_dir():
        raise PreflightError(f"init.checkpoint {folder} does not exist")
    fmt = detect_init_format(folder, cfg.init.format)
    if fmt == FORMAT_OURS:
        check_architecture(cfg.model, tokenizer, norm_stats, folder, "init.checkpoint")
    return fmt  # OpenVLA folders are checked key by key by the model's loader, which names every mismatch


def resolved_model_config(model_cfg: ModelConfig, tokenizer, norm_stats: dict | None) -> OpenFlyAgent:
    """The agent `model_cfg` gives with this tokenizer, built on the meta device (no memory, no compute)."""
    with torch.device("meta"):
        return OpenFlyAgent.from_model_config(model_cfg, tokenizer=tokenizer, norm_stats=norm_stats)


def check_architecture(model_cfg: ModelConfig, tokenizer, norm_stats, folder: Path, what: str) -> None:
    """Compare a checkpoint of ours with the configured model: config sections, then every tensor shape."""
    config_file = folder / C.CONFIG_NAME
    if not config_file.is_file():
        raise PreflightError(f"{what} {folder} has no {C.CONFIG_NAME}")
    meta = resolved_model_config(model_cfg, tokenizer, norm_stats)
    saved = json.loads(config_file.read_text()).get("agent", {})
    differences = diff_configs(_shape_relevant(meta.config.agent), _shape_relevant(saved))
    if differences:
        raise PreflightError(
            f"{what} {folder} was trained with another architecture:\n  "
            + "\n  ".join(differences)
            + "\n  set these fields as in its config.json, or choose another checkpoint"
        )
    if (folder / C.WEIGHTS_NAME).is_file() or (folder / C.WEIGHTS_INDEX_NAME).is_file():
        expected = {k: tuple(v.shape) for k, v in meta.state_dict().items()}
        compare_shapes(expected, checkpoint_tensor_shapes(folder), f"{what} {folder}")


def _shape_relevant(agent_config: dict) -> dict:
    """The config sections that decide tensor shapes (prompt text, thresholds and merging may differ)."""
    return {
        k: v
        for k, v in agent_config.items()
        if k in ("vision", "projector", "llm", "grounding", "action_head")
    }


def build_agent(
    cfg: TrainConfig, tokenizer, norm_stats: dict | None, init_format: str | None
) -> OpenFlyAgent:
    """A fresh agent, or one initialised from `init.checkpoint` (ours: from_pretrained; OpenVLA: by name)."""
    if init_format == FORMAT_OURS:
        agent = OpenFlyAgent.from_pretrained(cfg.init.checkpoint, tokenizer=tokenizer)
        logger.info("initialised from %s", cfg.init.checkpoint)
        return agent
    if init_format == FORMAT_OPENVLA:
        try:  # built on the meta device and filled once: one copy of the 7B weights in memory
            agent, report = agent_from_openvla_checkpoint(cfg.init.checkpoint, cfg.model, tokenizer=tokenizer)
        except ValueError as err:  # the loader names every unexpected / missing / mis-shaped key
            raise PreflightError(f"init.checkpoint: {err}") from err
        logger.info("initialised from the OpenVLA checkpoint %s: %s", cfg.init.checkpoint, report.summary())
        return agent.train()
    return OpenFlyAgent.from_model_config(cfg.model, tokenizer=tokenizer, norm_stats=norm_stats)


def majority_class_rate(
    train: NavigationStepDataset, test: NavigationStepDataset, indices: list[int]
) -> float:
    """Share of the evaluated test samples whose action is the train split's most frequent action."""
    counts = collections.Counter(int(e.actions[t]) for e, t in (train.locate(i) for i in range(len(train))))
    majority = counts.most_common(1)[0][0]
    hits = sum(int(e.actions[t]) == majority for e, t in (test.locate(i) for i in indices))
    logger.info("majority action of the train split: %d (%s)", majority, C.ACTION_NAMES[majority])
    return hits / max(len(indices), 1)
