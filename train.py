"""Train OpenFly-Agent, from one CPU to a GPU cluster (docs/TRAINING.md).

    accelerate launch train.py                                   # tiny preset, embedded-small data, CPU
    accelerate launch train.py --config_path configs/train/tiny.yaml --optim.lr=3e-4 --steps=500
    accelerate launch train.py --resume                      # continue <output_dir> from its last checkpoint
    accelerate launch --config_file configs/accelerate/fsdp.yaml train.py \
        --config_path configs/train/openfly-7b-full.yaml --init.checkpoint=/path/to/openvla-7b

Parses the config, generates the dataset when it is missing and calls `training.train` (all input checks
come first). Prints the final offline action accuracy next to the majority-class rate.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent
DEFAULT_CONFIG = REPO_ROOT / "configs" / "train" / "tiny.yaml"
EXIT_BAD_INPUT = 2

logger = logging.getLogger("train")


def parse_args(argv: list[str]):
    """`TrainConfig` from `--config_path` (default: the tiny preset) and dotted overrides; `--resume` alone
    means `--resume=true`."""
    from openfly_agent.training.config import TrainConfig
    from openfly_agent.utils.config import parse_config

    argv = ["--resume=true" if arg == "--resume" else arg for arg in argv]
    if not any(arg == "--config_path" or arg.startswith("--config_path=") for arg in argv):
        argv = ["--config_path", str(DEFAULT_CONFIG), *argv]
    return parse_config(TrainConfig, argv)


def ensure_dataset(cfg) -> None:
    """Generate the dataset with the toolchain when `data.root` has no train split (rank 0; others wait)."""
    from accelerate import PartialState

    from openfly_agent.data.openfly_reader import annotation_path
    from openfly_agent.training.accelerator import use_cpu

    if annotation_path(cfg.data.root, cfg.data.train_split).is_file() or not cfg.data.generate_if_missing:
        return
    state = PartialState(cpu=use_cpu(cfg))
    with state.main_process_first():
        if state.is_main_process:
            from openfly_agent.toolchain.config import GenerateConfig
            from openfly_agent.toolchain.generate import generate
            from openfly_agent.utils.config import load_yaml_config

            logger.info("%s has no dataset: generating it with %s", cfg.data.root, cfg.data.toolchain_config)
            overrides = [f"--output_dir={cfg.data.root}"]  # write where training reads
            generate(load_yaml_config(GenerateConfig, cfg.data.toolchain_config, overrides))


def report(result, cfg) -> None:
    """The final figures, on stdout of the main process."""
    final = result.final_metrics
    print(f"finished at step {result.state.step}; last checkpoint: {result.checkpoint}")
    if final:
        majority = final.get("majority_class_rate", float("nan"))
        print(
            f"offline action accuracy on {cfg.data.test_split} ({int(final['samples'])} samples): "
            f"{final['action_accuracy']:.4f}; majority-class rate: {majority:.4f}; "
            f"box IoU: {final['box_iou']:.4f}"
        )


def main(argv: list[str] | None = None) -> int:
    from draccus.utils import ParsingError

    from openfly_agent.training import PreflightError, train
    from openfly_agent.utils.errors import root_cause
    from openfly_agent.utils.logging_utils import setup_logging

    setup_logging()
    try:
        cfg = parse_args(sys.argv[1:] if argv is None else argv)
        ensure_dataset(cfg)
        result = train(cfg)
    except (ParsingError, PreflightError) as err:
        print(f"train.py: {root_cause(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if result.is_main_process:
        report(result, cfg)
    return 0


if __name__ == "__main__":
    sys.exit(main())
