"""train.py's command line: the config it parses, its `--help`, and the one-line messages of a run that fails.

train.py stays the short entry point (parse, `train(cfg)`, report); what
it prints for `--help`, for data that cannot be read and for Ctrl-C lives here. `unlisted` is the one place that
decides which options `--help` leaves out.
"""

from __future__ import annotations

from openfly_agent.constants import STAGE_GROUNDING, STAGE_RL
from openfly_agent.data.schema import SchemaError
from openfly_agent.model.config import VISION_DINOSIGLIP_224, VISION_TINY_CNN
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.config import TrainConfig
from openfly_agent.utils.cli_help import Unlisted, command_help
from openfly_agent.utils.config import REPO_ROOT, parse_config, with_config_path
from openfly_agent.utils.errors import RecordError, one_line, worker_error_name

DEFAULT_CONFIG = REPO_ROOT / "configs" / "train" / "tiny.yaml"

DESCRIPTION = (
    "Train OpenFly-Agent with accelerate, from one CPU to many GPUs (docs/TRAINING.md). Without --config_path "
    "the tiny preset runs on the embedded-small dataset, made beforehand (python -m openfly_agent.toolchain "
    "generate). Relative paths are relative to the working directory; the repository's own configs/ are found "
    "from anywhere."
)
EXAMPLES = (
    "accelerate launch train.py                                   # tiny preset, embedded-small data, CPU",
    "accelerate launch train.py --config_path configs/train/tiny.yaml --optim.lr=3e-4 --steps=500",
    "accelerate launch train.py --resume                          # continue <output_dir> from its last checkpoint",
    "accelerate launch --config_file configs/accelerate/fsdp.yaml train.py "
    "--config_path configs/train/openfly-7b-full.yaml --init.checkpoint=/path/to/openvla-7b "
    "--model.llm.tokenizer_path=/path/to/openvla-7b --data.root=/path/to/OpenFly",
)


# Settings the run derives, which `--help` never lists: each stays a field (a run's stored train_config.json and
# its model's config.json hold the resolved value, and a YAML file may pin it), but a value set by hand can only
# disagree with what the run derives.
DERIVED = (
    # the LLM variant's `default_vocab_size`: the tokenizer's length + 256 action ids (tiny), OpenVLA's 32064
    # (llama2-7b); model/factory.py::resolve_vocabulary fills it in
    "model.llm.vocab_size",
    # resolve_vocabulary replaces the three special ids by the tokenizer's, which every training run has
    "model.llm.bos_token_id",
    "model.llm.eos_token_id",
    "model.llm.pad_token_id",
    # the end of the 256 action ids: null takes the vocabulary resolve_vocabulary fills in (tiny: the trained
    # tokenizer's + 256); the llama2-7b presets pin OpenVLA's 32000 (the last ids of the Llama-2 tokenizer)
    "model.action_head.vocab_end",
    # the embedded city's vocabulary sizes (sim/city_vocab.py): training/builder.py::attribute_lookup refuses any
    # other value
    "model.grounding.attribute_classes",
    # a Llama-2 token id that the released OpenVLA prompt format appends (29871 '▁', the openvla-compat-7b
    # preset); no other prompt has one
    "model.prompt.suffix_token_id",
)
# the vision fields a backbone fixes (its config refuses any other value): the ResNet's stride of 16; the
# dinosiglip ViTs' 224 px and patch 14
FIXED_BY_VISION = {
    VISION_TINY_CNN: ("model.vision.patch_size",),
    VISION_DINOSIGLIP_224: ("model.vision.image_size", "model.vision.patch_size"),
}
# what `--help` needs to get past the checks of a run it lists (stage=rl needs a checkpoint, stage=grounding a
# grounding dataset, steps=null an epoch count); filled only where the command needs them, and shown unset
HELP_PLACEHOLDERS = {"init.checkpoint": "CHECKPOINT", "data.grounding_root": "GROUNDING_ROOT", "epochs": "1"}


def unlisted(cfg: TrainConfig) -> list[Unlisted]:
    """The options `--help` leaves out for the run `cfg` describes (each still accepted): the sections and fields
    of a stage, freeze stage or setting it does not use, and the settings it derives (`DERIVED`, `FIXED_BY_VISION`).
    """
    groups = []
    if cfg.stage != STAGE_RL:
        groups.append(Unlisted(("rl",), "the RL stage's", "--stage=rl"))
    if not cfg.use_lora:
        groups.append(Unlisted(("lora",), "LoRA's", "--freeze_stage=lora"))
    if cfg.stage != STAGE_GROUNDING:
        grounding = ("data.grounding_root", "data.instruction_fraction", "data.expressions_per_frame")
        groups.append(
            Unlisted(
                (*grounding, "model.prompt.grounding_template"), "the grounding stage's", "--stage=grounding"
            )
        )
    if not cfg.model.llm.trains_own_tokenizer:
        groups.append(Unlisted(("tokenizer",), "the tiny LLM's tokenizer", "--model.llm.type=tiny"))
    if cfg.steps is not None:
        groups.append(Unlisted(("epochs",), "used only when steps is null", "--steps=null"))
    if cfg.init.checkpoint is None:
        groups.append(Unlisted(("init.matching",), "a checkpoint's", "--init.checkpoint=DIR"))
    if cfg.time_limit_minutes is None:
        groups.append(Unlisted(("optim.horizon",), "a time limit's", "--time_limit_minutes=MIN"))
    derived = (*DERIVED, *FIXED_BY_VISION.get(cfg.model.vision.type, ()))
    why = "derived by the run or fixed by the model's variants and presets (training/cli.py)"
    groups.append(Unlisted(derived, why))
    return groups


def with_default_config(argv: list[str]) -> list[str]:
    """`argv` with the tiny preset when no config is given."""
    return with_config_path(argv, DEFAULT_CONFIG)


def parse_args(argv: list[str]):
    """`TrainConfig` from `--config_path` (default: the tiny preset) and dotted overrides."""
    return parse_config(TrainConfig, with_default_config(argv))


def help_text(argv: list[str]) -> str:
    """`--help`: every option that applies to the run the command line describes (`unlisted` names the others),
    with the value the same command line without `--help` would use."""
    return command_help(
        TrainConfig,
        with_default_config(argv),
        "train.py",
        DESCRIPTION,
        EXAMPLES,
        placeholders=HELP_PLACEHOLDERS,
        unlisted=unlisted,
    )


def data_error_message(err: BaseException) -> str | None:
    """The one line (file, record, field) of a dataset that cannot be read, or None for any other error.

    Covers the reader's and the frame store's errors raised in this process, before or during training, and
    the same errors raised inside a DataLoader worker (torch re-raises those as a RuntimeError).
    """
    data_errors = (SchemaError, RecordError)
    if isinstance(err, data_errors) or worker_error_name(err) in {e.__name__ for e in data_errors}:
        return one_line(err)
    return None


def interrupted_message(output_dir: str | None) -> str:
    """What Ctrl-C prints: how to pick the run up again."""
    latest = CheckpointManager(output_dir, keep_last=1).latest() if output_dir else None
    if latest is None:
        return "train.py: interrupted before the first checkpoint; run the same command again to start over"
    return f"train.py: interrupted; run the same command with --resume to resume from {latest}"
