"""Action statistics in the OpenVLA `dataset_statistics` format, for the `openvla_bins` action head.

The 8-dim vectors are one-hot-like codes (constants.OPENVLA_ACTION_VECTORS). OpenVLA normalises each
dim with its 1st / 99th percentiles; a code value outside [q01, q99] is clipped and cannot be decoded
back (a rare action with q01 == q99 == 0 decodes to 0, docs/OFFICIAL_OPENFLY.md 1.6 and 10). So on every
dim where the percentiles would clip a value that occurs, or the 0 code ("not this action"), q01 / q99
are widened to min(min, 0) / max(max, 0).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode

logger = logging.getLogger(__name__)


def action_vectors(actions: Iterable[int]) -> np.ndarray:
    """Model action ids (0..9) -> (N, 8) float32 OpenVLA vectors."""
    ids = [int(a) for a in actions]
    bad = [a for a in ids if a not in C.OPENVLA_ACTION_VECTORS]
    if bad:
        raise ValueError(f"action ids {sorted(set(bad))} have no 8-dim vector; only 0..9 do")
    if not ids:
        return np.zeros((0, C.OPENVLA_ACTION_DIM), dtype=np.float32)
    return np.asarray([C.OPENVLA_ACTION_VECTORS[a] for a in ids], dtype=np.float32)


def _model_actions(episode: Episode) -> np.ndarray:
    """The steps of `episode` a model is trained on: ids 0..9 (take-off / landing phases skipped)."""
    return episode.actions[(episode.actions >= 0) & (episode.actions < C.NUM_ACTIONS)]


def compute_action_statistics(episodes: Iterable[Episode]) -> dict:
    """OpenVLA statistics of the 8-dim action vectors of every model step (ids 0..9) in `episodes`.

    Returns:
        {"action": {"mean", "std", "max", "min", "q01", "q99", "mask"} (8 values each),
        "num_transitions", "num_trajectories"}. `mask` is all True (every dim is un-normalised).
        q01 / q99 are the 1st / 99th percentiles, widened to min(min, 0) / max(max, 0) on any dim where
        they would clip a value that occurs or 0; so every used dim has q01 < q99 and every code value
        survives normalise -> un-normalise; unused dims have q01 == q99 == 0.

    Raises:
        ValueError: no model step at all.
    """
    per_episode = [_model_actions(e) for e in episodes]
    per_episode = [a for a in per_episode if len(a)]
    if not per_episode:
        raise ValueError("no model actions (ids 0..9) in the episodes: cannot compute action statistics")
    vectors = action_vectors(np.concatenate(per_episode)).astype(np.float64)  # (N, 8)
    lo, hi = vectors.min(axis=0), vectors.max(axis=0)  # (8,)
    q01, q99 = np.quantile(vectors, 0.01, axis=0), np.quantile(vectors, 0.99, axis=0)
    lo_code, hi_code = np.minimum(lo, 0.0), np.maximum(hi, 0.0)  # the range must hold 0 and every value
    widened = (q01 > lo_code) | (q99 < hi_code)
    if widened.any():
        logger.info(
            "action statistics: q01/q99 widened to min/max on dims %s", np.flatnonzero(widened).tolist()
        )
    q01, q99 = np.where(widened, lo_code, q01), np.where(widened, hi_code, q99)
    return {
        "action": {
            "mean": vectors.mean(axis=0).tolist(),
            "std": vectors.std(axis=0).tolist(),
            "max": hi.tolist(),
            "min": lo.tolist(),
            "q01": q01.tolist(),
            "q99": q99.tolist(),
            "mask": [True] * C.OPENVLA_ACTION_DIM,
        },
        "num_transitions": int(len(vectors)),
        "num_trajectories": len(per_episode),
    }


def action_histogram(episodes: Iterable[Episode]) -> dict[int, int]:
    """Count of each action id (including -1 / -2) over all frames."""
    counts: dict[int, int] = {}
    for episode in episodes:
        ids, n = np.unique(episode.actions, return_counts=True)
        for a, k in zip(ids.tolist(), n.tolist()):
            counts[a] = counts.get(a, 0) + k
    return dict(sorted(counts.items()))
