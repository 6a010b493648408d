"""95 % intervals of the evaluation's numbers, and the one form every table prints them in.

A rate (SR, OSR: k successes of n episodes) gets the Wilson score interval; a mean of per-episode values (SPL,
NE) a percentile bootstrap over the episodes with a fixed seed, so the same episodes always give the same
interval (a resumed run's tables equal an uninterrupted one's). docs/METRICS.md, "Intervals".
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

Z_95 = 1.959963984540054  # standard normal quantile at 0.975: a two-sided 95 % interval
BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0
_BOOTSTRAP_CHUNK_VALUES = 4_000_000  # resampled values drawn at once (bounds the memory of large runs)


def wilson_interval(successes: int, trials: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval of the rate `successes / trials`, as fractions in [0, 1].

    (p + z^2 / 2n -+ z sqrt(p (1 - p) / n + z^2 / 4n^2)) / (1 + z^2 / n) with p = k / n. Unlike the normal
    approximation it stays inside [0, 1] and is not empty at 0 or n successes (0 of 260 gives 0-1.5 %).
    """
    if trials <= 0:
        raise ValueError(f"wilson_interval needs trials >= 1, got {trials}")
    if not 0 <= successes <= trials:
        raise ValueError(f"wilson_interval: successes {successes} outside 0..{trials}")
    p, n, z2 = successes / trials, trials, z * z
    centre = p + z2 / (2 * n)
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    scale = 1 + z2 / n
    return max(0.0, (centre - half) / scale), min(1.0, (centre + half) / scale)


def bootstrap_mean_interval(
    values: Sequence[float],
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
    level: float = 0.95,
) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean of `values`: the (1 - level) / 2 and (1 + level) / 2
    quantiles of the means of `resamples` resamples (with replacement, of the same size), drawn with
    `numpy.random.default_rng(seed)` over the sorted values (so the interval does not depend on their order)."""
    data = np.sort(np.asarray(values, dtype=np.float64))  # (n,)
    if data.ndim != 1 or len(data) == 0:
        raise ValueError(f"bootstrap_mean_interval needs a non-empty 1-D sequence, got shape {data.shape}")
    if resamples < 1 or not 0 < level < 1:
        raise ValueError(
            f"bootstrap_mean_interval: resamples {resamples} < 1 or level {level} outside (0, 1)"
        )
    rng = np.random.default_rng(seed)
    n = len(data)
    per_chunk = max(1, _BOOTSTRAP_CHUNK_VALUES // n)
    means = []
    for start in range(0, resamples, per_chunk):
        count = min(per_chunk, resamples - start)
        means.append(data[rng.integers(0, n, size=(count, n))].mean(axis=1))  # (count,)
    tail = (1 - level) / 2
    low, high = np.quantile(np.concatenate(means), [tail, 1 - tail])
    return float(low), float(high)


def format_interval(value: float, interval: Sequence[float] | None, decimals: int = 1) -> str:
    """`29.2 (20.9-39.1)`: the value and its interval, the one form every table uses (the value alone
    without an interval)."""
    text = f"{value:.{decimals}f}"
    if interval is None:
        return text
    low, high = interval
    return f"{text} ({low:.{decimals}f}-{high:.{decimals}f})"
