"""Two navigation runs' held-out action predictions on the same samples, paired by episode.

A run's offline `action_accuracy` (training/evaluate.py) is one mean over a split's steps. Two runs that read the
same split (their history or memory may differ: the samples are the same steps of the same episodes) are compared
here step by step: both accuracies, the steps only one of them predicts, and the difference with a 95 % interval
from a bootstrap over episodes (the steps of one episode are not independent, so whole episodes are resampled,
the same ones for both runs). Read it where closed-loop success rates sit at the floor and an arm's effect can
only show in what its network predicts.

    python bench/offline_compare.py --run current_frame=<arm>/navigation --run keyframes=<arm>/navigation
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from openfly_agent import constants as C
from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.model.persistence.checkpoint_path import resolve_checkpoint_folder
from openfly_agent.rollout.stats import BOOTSTRAP_RESAMPLES, BOOTSTRAP_SEED
from openfly_agent.training.builder import load_splits
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.evaluate import eval_indices
from openfly_agent.training.stages import stage_data
from openfly_agent.utils.config import config_from_dict, replace

logger = logging.getLogger(__name__)


@dataclass
class StepHits:
    """Whether a run predicts each sample's action, keyed by (episode id, step)."""

    keys: list[tuple[str, int]]  # (episode_id, step index) of each sample, in the split's order
    hits: np.ndarray  # (N,) float: the share of the sample's action tokens predicted (1 token: 0 or 1)
    split: str

    @property
    def accuracy(self) -> float:
        return float(self.hits.mean()) if len(self.hits) else float("nan")


def collect_step_hits(
    run_dir: str | Path,
    split: str | None = None,
    max_samples: int | None = None,
    batch_size: int = 32,
) -> StepHits:
    """Run a navigation run's agent (its last checkpoint) over evenly spaced samples of a split.

    Args:
        run_dir: the training run (its `train_config.json` says the data and history; relative paths in it are read
            from the current directory, as the run read them).
        split: the split to read (default: the run's `data.test_split`).
        max_samples: evenly spaced samples of the split (None: all of them), as the training's own pass picks them.
        batch_size: samples per forward.

    Raises:
        FileNotFoundError: no `train_config.json` in `run_dir`, or no checkpoint.
        ValueError: a grounding-stage run (it has no action targets), or a sample without an action token.
    """
    config_path = Path(run_dir) / C.TRAIN_CONFIG_NAME
    if not config_path.is_file():
        raise FileNotFoundError(f"{run_dir} is not a training run: no {C.TRAIN_CONFIG_NAME}")
    saved = json.loads(config_path.read_text())
    if saved.get("stage") == C.STAGE_GROUNDING:
        raise ValueError(f"{run_dir} is a grounding-stage run: it predicts no actions")
    cfg = config_from_dict(TrainConfig, saved)
    if split:
        cfg = replace(cfg, data=replace(cfg.data, test_split=split))
    folder = resolve_checkpoint_folder(run_dir)
    if folder is None:
        raise FileNotFoundError(f"no checkpoint at {run_dir}")
    agent = OpenFlyAgent.from_pretrained(str(folder)).eval()
    data = stage_data(cfg, load_splits(cfg.data, cfg.model.grounding), agent)
    indices = eval_indices(len(data.test), max_samples)
    keys, hits = [], []
    with torch.no_grad():
        for first in range(0, len(indices), batch_size):
            samples = [data.test[i] for i in indices[first : first + batch_size]]
            keys += [(s[C.EPISODE_ID], int(s[C.STEP_INDEX])) for s in samples]
            batch = data.collate(samples)
            outputs: dict = {}
            agent(batch, outputs=outputs)
            # (n,) each: the n labelled tokens in row-major order, as the action loss reads them
            hit, is_action = agent.action_hits(outputs["action_logits"], outputs["action_targets"])
            rows = (batch[C.LABELS] != C.IGNORE_INDEX).nonzero()[:, 0]  # (n,): the sample of each token
            tokens = torch.bincount(rows[is_action], minlength=len(samples))  # (B,)
            if bool((tokens == 0).any()):
                raise ValueError(f"{run_dir}: a sample of {cfg.data.test_split} has no action token")
            right = torch.bincount(rows[is_action], weights=hit[is_action].double(), minlength=len(samples))
            hits.append((right / tokens).numpy())
    logger.info("%s: %d samples of %s", run_dir, len(keys), cfg.data.test_split)
    return StepHits(keys, np.concatenate([np.zeros(0), *hits]), cfg.data.test_split)


def episode_bootstrap_interval(
    episodes: list[str],
    hits_a: np.ndarray,
    hits_b: np.ndarray,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
    level: float = 0.95,
) -> tuple[float, float, float]:
    """(accuracy B - accuracy A, lower, upper) over paired samples, the percentile interval of a bootstrap that
    resamples whole episodes with replacement (the same episodes for both runs in each resample).

    Args:
        episodes: the episode id of each sample (N,).
        hits_a, hits_b: (N,) per-sample hits of the two runs on the same samples.
    """
    if not len(episodes) == len(hits_a) == len(hits_b) or not episodes:
        raise ValueError(
            f"need aligned, non-empty samples, got {len(episodes)} / {len(hits_a)} / {len(hits_b)}"
        )
    names, episode_of = np.unique(np.asarray(episodes), return_inverse=True)  # episode_of: (N,)
    count = np.bincount(episode_of).astype(np.float64)  # (E,) samples per episode
    gain = np.bincount(
        episode_of, weights=np.asarray(hits_b, np.float64) - np.asarray(hits_a, np.float64)
    )  # (E,)
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(names), size=(resamples, len(names)))  # (R, E) episodes drawn
    rows = np.arange(resamples)[:, None] * len(names)  # (R, 1)
    weights = np.bincount((rows + draws).ravel(), minlength=resamples * len(names))  # how often each is drawn
    weights = weights.reshape(resamples, len(names)).astype(np.float64)  # (R, E)
    diffs = (weights @ gain) / (weights @ count)  # (R,)
    tail = (1.0 - level) / 2.0
    lower, upper = np.quantile(diffs, [tail, 1.0 - tail])
    return float(gain.sum() / count.sum()), float(lower), float(upper)


def paired_hits(
    a: StepHits, b: StepHits, resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED
) -> dict:
    """The figures of two runs on the same samples: accuracies, samples only one predicts, the paired difference
    (B - A) with its episode-bootstrap interval.

    Raises:
        ValueError: the runs read different samples (the first differing one is named).
    """
    if a.keys != b.keys:
        if len(a.keys) != len(b.keys):
            raise ValueError(
                f"the runs read {len(a.keys)} and {len(b.keys)} samples: not the same split and subset"
            )
        first = next(i for i, (x, y) in enumerate(zip(a.keys, b.keys)) if x != y)
        raise ValueError(f"sample {first} differs: {a.keys[first]} against {b.keys[first]}")
    episodes = [episode for episode, _ in a.keys]
    diff, lower, upper = episode_bootstrap_interval(episodes, a.hits, b.hits, resamples, seed)
    return {
        "split": a.split,
        "samples": len(a.keys),
        "episodes": len(set(episodes)),
        "accuracy_a": a.accuracy,
        "accuracy_b": b.accuracy,
        "only_a": int(((a.hits == 1) & (b.hits == 0)).sum()),
        "only_b": int(((b.hits == 1) & (a.hits == 0)).sum()),
        "diff": diff,
        "diff_ci95": [lower, upper],
        "resamples": resamples,
    }


def paired_markdown(figures: dict, name_a: str, name_b: str) -> str:
    """One table of `paired_hits`' figures, accuracies in percent."""
    low, high = figures["diff_ci95"]
    return "\n".join(
        [
            f"Held-out action accuracy, {figures['split']}: {figures['samples']} samples of "
            f"{figures['episodes']} episodes, the same in both runs",
            "",
            f"| {name_a} | {name_b} | {name_b} - {name_a} (pp) [95 % CI, episodes resampled] | "
            f"only {name_a} right | only {name_b} right |",
            "|---:|---:|---:|---:|---:|",
            f"| {100 * figures['accuracy_a']:.1f} | {100 * figures['accuracy_b']:.1f} | "
            f"{100 * figures['diff']:+.1f} [{100 * low:+.1f}, {100 * high:+.1f}] | "
            f"{figures['only_a']} | {figures['only_b']} |",
            "",
        ]
    )
