"""What a run trains on and with: the dataset splits, the tokenizer, and the agent (fresh or initialised).

Every check that can fail on user input runs before the agent's weights are built or read.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import torch
from accelerate import Accelerator
from accelerate.utils import DistributedType, set_seed

from openfly_agent import constants as C
from openfly_agent.data.config import DataConfig
from openfly_agent.data.dataset import NavigationStepDataset
from openfly_agent.data.frames import FrameStore, FrameStores
from openfly_agent.data.grounding import read_grounding_expressions
from openfly_agent.data.schema import Episode
from openfly_agent.data.stats import compute_action_statistics
from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.model.config import (
    HEAD_OPENVLA_BINS,
    CellGroundingConfig,
    GroundingConfig,
    ModelConfig,
)
from openfly_agent.model.language.tokenizer import load_tokenizer, train_bpe_tokenizer
from openfly_agent.model.persistence.checkpoint_path import (
    UnreadableWeightsError,
    check_weights_readable,
    resolve_checkpoint_folder,
)
from openfly_agent.model.persistence.openvla_loader import agent_from_openvla_checkpoint
from openfly_agent.model.pretrained_config import OpenFlyAgentConfig
from openfly_agent.training.attribute_targets import LandmarkAttributes, vocabulary_sizes
from openfly_agent.training.config import STAGE_GROUNDING, InitConfig, TrainConfig
from openfly_agent.training.init_matching import load_matching_weights
from openfly_agent.training.modes import apply_training_mode
from openfly_agent.training.preflight import (
    PreflightError,
    check_frames_readable,
    checkpoint_tensor_shapes,
    compare_shapes,
    diff_configs,
    load_split,
)

logger = logging.getLogger(__name__)

TOKENIZER_DIR = "tokenizer"
FORMAT_OURS, FORMAT_OPENVLA = "openfly", "openvla"


@dataclass
class Splits:
    """The episodes of each configured split (read and checked) and the frames they read.

    The train split also holds the train episodes of `data.extra_train_roots` (e.g. DAgger rollouts), each read
    from its own root.
    """

    episodes: dict[str, list[Episode]]
    frames: FrameStore | FrameStores
    # (scene id, landmark id) -> (4,) attribute ids, with `model.grounding.attribute_weight` (attribute_targets.py)
    attributes: LandmarkAttributes | None = None

    def dataset(
        self, split: str, cfg: TrainConfig, agent: OpenFlyAgent, history: str | None = None
    ) -> NavigationStepDataset:
        """Per-step samples of `split`: the history mode of `cfg.data` (or `history`), the agent's memory shape
        and keyframes."""
        return NavigationStepDataset(
            self.episodes[split],
            self.frames,
            history or cfg.data.history.mode,
            capacity=cfg.model.memory.capacity,
            set_size=cfg.model.keyframes.set_size,
            keyframe_selector=agent.network.keyframe_selector,
            seed=cfg.seed,
            target_attributes=self.attributes,
        )


def load_splits(data: DataConfig, grounding: GroundingConfig) -> Splits:
    """Read the train, validation and test splits (and the train splits of `data.extra_train_roots`), with the
    target attributes when the `grounding` head learns them; a bad record or unreadable frames is a
    `PreflightError`."""
    names = dict.fromkeys((C.SPLIT_TRAIN, data.val_split, data.test_split))
    episodes = {split: load_split(data, split) for split in names}
    frames = FrameStore(data.root, cache_episodes=data.cache_episodes, cache_frames=data.cache_frames)
    check_frames_readable(frames, episodes[C.SPLIT_TRAIN])
    attributes = attribute_lookup(grounding, data.root)
    if not data.extra_train_roots:
        return Splits(episodes, frames, attributes)
    stores = [(frames, [e for split in names for e in episodes[split]])]
    for root in data.extra_train_roots:
        extra = load_split(dataclasses.replace(data, root=root), C.SPLIT_TRAIN)
        store = FrameStore(root, cache_episodes=data.cache_episodes, cache_frames=data.cache_frames)
        check_frames_readable(store, extra)
        logger.info("%d more train episodes from %s", len(extra), root)
        stores.append((store, extra))
        episodes[C.SPLIT_TRAIN] = episodes[C.SPLIT_TRAIN] + extra
    try:
        return Splits(episodes, FrameStores(stores), attributes)
    except ValueError as err:  # an episode id in two roots
        raise PreflightError(f"data.extra_train_roots: {err}") from err


def attribute_lookup(grounding: GroundingConfig, data_root: str) -> LandmarkAttributes | None:
    """The target attributes' lookup of the dataset at `data_root` when the grounding head learns them
    (`model.grounding.attribute_weight` or `colour_vocabulary`, the cells head's)."""
    if not (
        isinstance(grounding, CellGroundingConfig)
        and (grounding.attribute_weight or grounding.colour_vocabulary)
    ):
        return None
    option = "attribute_weight" if grounding.attribute_weight else "colour_vocabulary"  # named in the errors
    if list(grounding.attribute_classes) != vocabulary_sizes():
        raise PreflightError(
            f"model.grounding.attribute_classes={grounding.attribute_classes} != the embedded city's vocabularies "
            f"{vocabulary_sizes()} (colour, type, size, feature)"
        )
    try:
        return LandmarkAttributes.for_dataset(data_root)
    except FileNotFoundError as err:
        raise PreflightError(f"model.grounding.{option} needs an embedded-city dataset: {err}") from err


def prepare_agent(
    cfg: TrainConfig, splits: Splits, accelerator: Accelerator, resume_from: Path | None
) -> OpenFlyAgent:
    """The agent to train: tokenizer, norm stats and checkpoints checked first, then built (or loaded), with
    the freeze stage or LoRA adapters and gradient checkpointing applied."""
    train_episodes = splits.episodes[C.SPLIT_TRAIN]
    tokenizer = resolve_tokenizer(cfg, train_episodes, accelerator)
    norm_stats = None
    if cfg.model.action_head.type == HEAD_OPENVLA_BINS:
        norm_stats = {Path(cfg.data.root).name: compute_action_statistics(train_episodes)}
    init_format = check_init_checkpoint(cfg.init, cfg.model, tokenizer, norm_stats)
    if resume_from is not None:
        check_architecture(cfg.model, tokenizer, norm_stats, resume_from, "the checkpoint to resume")
    set_seed(cfg.seed)  # the same initial weights on every process and on resume
    agent = build_agent(cfg, tokenizer, norm_stats, init_format)
    apply_training_mode(agent, cfg)
    if accelerator.distributed_type == DistributedType.FSDP:
        make_parameters_contiguous(agent)
    return agent


def make_parameters_contiguous(module: torch.nn.Module) -> None:
    """Give every parameter a contiguous layout, in place, values unchanged: FSDP shards only contiguous
    parameters, and the tiny preset's ResNet keeps its weights channels-last (oneDNN's fast path on CPUs; the
    unsharded runs keep that layout, so their numbers stay those of the recorded runs)."""
    for param in module.parameters():
        if not param.is_contiguous():
            param.data = param.data.contiguous()


def resolve_tokenizer(cfg: TrainConfig, train_episodes: list, accelerator: Accelerator):
    """The run's tokenizer (order in `TokenizerConfig`); a trained one is written by rank 0 first."""
    path = cfg.model.llm.tokenizer_path
    if path and not Path(path).is_dir():
        raise PreflightError(
            f"--model.llm.tokenizer_path {path} is not a folder: pass a local tokenizer folder (nothing is "
            "downloaded)"
        )
    candidates = [path]
    if cfg.init.checkpoint and Path(cfg.init.checkpoint).exists():  # a run folder: its `last` checkpoint
        init_folder = init_checkpoint_folder(cfg.init.checkpoint)
        if (init_folder / "tokenizer_config.json").is_file():
            candidates.append(str(init_folder))
    own = Path(cfg.output_dir) / TOKENIZER_DIR
    for folder in [c for c in candidates if c]:
        logger.info("tokenizer: %s", folder)
        return load_tokenizer(folder)
    if not cfg.model.llm.trains_own_tokenizer and not (own / "tokenizer_config.json").is_file():
        raise PreflightError(
            f"llm.type={cfg.model.llm.type} needs its tokenizer: set --model.llm.tokenizer_path to a "
            "local folder (nothing is downloaded)"
        )
    with accelerator.main_process_first():
        if not (own / "tokenizer_config.json").is_file():
            texts = sorted({e.instruction for e in train_episodes})
            if cfg.stage == STAGE_GROUNDING and cfg.data.grounding_root:  # the expressions' words too
                texts += sorted(read_grounding_expressions(cfg.data.grounding_root))
            logger.info(
                "training a BPE tokenizer (%d tokens) on %d instructions -> %s",
                cfg.tokenizer.train_vocab_size,
                len(texts),
                own,
            )
            return train_bpe_tokenizer(texts, cfg.tokenizer.train_vocab_size, out_dir=own)
        return load_tokenizer(own)


def init_checkpoint_folder(path: str) -> Path:
    """The folder `init.checkpoint` names (a run folder or its `last` pointer: the checkpoint it points at); a
    folder that is none of these (a dataset, say) is a `PreflightError`."""
    try:
        return resolve_checkpoint_folder(path) or Path(path)
    except FileNotFoundError as err:
        raise PreflightError(f"init.checkpoint: {err}") from None


def detect_init_format(folder: Path) -> str:
    """`openfly` when config.json carries our model_type, else `openvla`."""
    config = folder / C.CONFIG_NAME
    if not config.is_file():
        raise PreflightError(
            f"init.checkpoint {folder} has no {C.CONFIG_NAME}: not a Hugging Face model folder"
        )
    model_type = json.loads(config.read_text()).get("model_type")
    return FORMAT_OURS if model_type == C.MODEL_TYPE else FORMAT_OPENVLA


def check_init_checkpoint(
    init: InitConfig, model_cfg: ModelConfig, tokenizer, norm_stats: dict | None
) -> str | None:
    """Validate `init.checkpoint` against the model config before any weight is read; return its format."""
    if init.checkpoint is None:
        return None
    folder = Path(init.checkpoint)
    if not folder.is_dir():
        raise PreflightError(f"init.checkpoint {folder} does not exist")
    folder = init_checkpoint_folder(init.checkpoint)  # a training run or its `last`: its checkpoint
    try:
        check_weights_readable(folder)
    except UnreadableWeightsError as err:
        raise PreflightError(f"init.checkpoint: {err}") from None
    fmt = detect_init_format(folder)
    if init.matching and fmt != FORMAT_OURS:
        raise PreflightError(f"init.matching loads checkpoints of ours; {folder} is an {fmt} checkpoint")
    if fmt == FORMAT_OURS and not init.matching:
        check_architecture(model_cfg, tokenizer, norm_stats, folder, "init.checkpoint")
    return fmt  # OpenVLA folders are checked key by key by the model's loader, which names every mismatch


def meta_agent(model_cfg: ModelConfig, tokenizer, norm_stats: dict | None) -> OpenFlyAgent:
    """The agent `model_cfg` gives with this tokenizer, built on the meta device (no memory, no compute)."""
    with torch.device("meta"):
        return OpenFlyAgent.from_model_config(model_cfg, tokenizer=tokenizer, norm_stats=norm_stats)


def check_architecture(model_cfg: ModelConfig, tokenizer, norm_stats, folder: Path, what: str) -> None:
    """Compare a checkpoint of ours with the configured model: config sections, then every tensor shape."""
    config_file = folder / C.CONFIG_NAME
    if not config_file.is_file():
        raise PreflightError(f"{what} {folder} has no {C.CONFIG_NAME}")
    meta = meta_agent(model_cfg, tokenizer, norm_stats)
    try:  # an older config.json in today's layout, as loading the checkpoint reads it
        saved = OpenFlyAgentConfig(agent=json.loads(config_file.read_text()).get("agent", {})).agent
    except ValueError as err:
        raise PreflightError(f"{what} {folder}/{C.CONFIG_NAME}: {err}") from None
    differences = diff_configs(_shape_relevant(meta.config.agent), _shape_relevant(saved))
    if differences:
        raise PreflightError(
            f"{what} {folder} was trained with another architecture:\n  "
            + "\n  ".join(differences)
            + "\n  set these fields as in its config.json, or choose another checkpoint"
        )
    if (folder / C.WEIGHTS_NAME).is_file() or (folder / C.WEIGHTS_INDEX_NAME).is_file():
        expected = {k: tuple(v.shape) for k, v in meta.network.state_dict().items()}  # the saved names
        compare_shapes(expected, checkpoint_tensor_shapes(folder), f"{what} {folder}")


def _shape_relevant(agent_config: dict) -> dict:
    """The config sections that decide tensor shapes (prompt text, thresholds and merging may differ)."""
    return {k: v for k, v in agent_config.items() if k in ("vision", "llm", "grounding", "action_head")}


def build_agent(
    cfg: TrainConfig, tokenizer, norm_stats: dict | None, init_format: str | None
) -> OpenFlyAgent:
    """A fresh agent, or one initialised from `init.checkpoint` (ours: from_pretrained, or the matching tensors
    with `init.matching`; OpenVLA: by name)."""
    if init_format == FORMAT_OURS and cfg.init.matching:
        agent = OpenFlyAgent.from_model_config(cfg.model, tokenizer=tokenizer, norm_stats=norm_stats)
        report = load_matching_weights(agent.network, Path(cfg.init.checkpoint))  # the saved names
        logger.info("initialised from %s: %s", cfg.init.checkpoint, report.summary())
        return agent
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
