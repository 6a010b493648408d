"""Statistics of two policies flown on the same episodes (paired outcomes), as pure functions.

- `mcnemar_exact_p(b, c)`: the exact McNemar test, a two-sided binomial test of the discordant pairs at p = 1/2.
- `newcombe_paired_interval(...)`: the 95 % interval of a difference of paired proportions, Newcombe's method 10
  (Newcombe 1998, Statistics in Medicine 17:2635-2650): Wilson score limits of each proportion combined with
  the phi correlation of the 2 x 2 table.
- `paired_bootstrap_interval(a, b)`: the percentile interval of mean(b - a) over episodes resampled with
  replacement (the same episodes for both policies in each resample), with a fixed seed.

No scipy: the binomial tail is a sum of `math.comb`; the Wilson limits and the bootstrap are rollout/stats.py's.
docs/METRICS.md ("Paired comparison") states what each number means.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from openfly_agent.rollout.stats import (
    BOOTSTRAP_RESAMPLES,
    BOOTSTRAP_SEED,
    Z_95,
    bootstrap_mean_interval,
    wilson_interval,
)


@dataclass(frozen=True)
class PairedCounts:
    """The 2 x 2 table of paired binary outcomes (A's success, B's success) over the same episodes."""

    both: int  # A and B succeed
    only_a: int  # A succeeds, B fails
    only_b: int  # B succeeds, A fails
    neither: int

    @property
    def n(self) -> int:
        return self.both + self.only_a + self.only_b + self.neither

    @classmethod
    def of(cls, a: Sequence[bool], b: Sequence[bool]) -> PairedCounts:
        """Counts of two aligned outcome lists (episode i of `a` is episode i of `b`)."""
        if len(a) != len(b):
            raise ValueError(f"paired outcomes of different lengths: {len(a)} and {len(b)}")
        pairs = [(bool(x), bool(y)) for x, y in zip(a, b)]
        return cls(
            both=pairs.count((True, True)),
            only_a=pairs.count((True, False)),
            only_b=pairs.count((False, True)),
            neither=pairs.count((False, False)),
        )


def mcnemar_exact_p(b: int, c: int) -> float:
    """Two-sided exact McNemar p-value of `b` and `c` discordant pairs: 2 P(X <= min(b, c)), X ~ Bin(b + c, 1/2),
    capped at 1 (1 when there is no discordant pair)."""
    if b < 0 or c < 0:
        raise ValueError(f"discordant counts must be >= 0, got {b} and {c}")
    n = b + c
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, k) for k in range(min(b, c) + 1))
    return min(1.0, 2 * tail / 2**n)


def newcombe_paired_interval(counts: PairedCounts, z: float = Z_95) -> tuple[float, float, float]:
    """(difference, lower, upper) of p_B - p_A, Newcombe's method 10 (no continuity correction), as fractions.

    With p1 = p_B, p2 = p_A, Wilson limits (l1, u1) and (l2, u2) and phi the correlation of the table (0 when a
    margin is empty): lower = d - sqrt((p1 - l1)^2 - 2 phi (p1 - l1)(u2 - p2) + (u2 - p2)^2), upper = d +
    sqrt((u1 - p1)^2 - 2 phi (u1 - p1)(p2 - l2) + (p2 - l2)^2).
    """
    n = counts.n
    if n < 1:
        raise ValueError("newcombe_paired_interval needs at least one pair")
    b_successes, a_successes = counts.both + counts.only_b, counts.both + counts.only_a
    p1, p2 = b_successes / n, a_successes / n
    l1, u1 = wilson_interval(b_successes, n, z)
    l2, u2 = wilson_interval(a_successes, n, z)
    # the table with B as the first variable: a = both, b = only B, c = only A, d = neither
    margins = b_successes * (n - b_successes) * a_successes * (n - a_successes)
    cross = counts.both * counts.neither - counts.only_b * counts.only_a
    phi = cross / math.sqrt(margins) if margins else 0.0
    difference = p1 - p2
    lower = difference - math.sqrt(
        max(0.0, (p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2)
    )
    upper = difference + math.sqrt(
        max(0.0, (u1 - p1) ** 2 - 2 * phi * (u1 - p1) * (p2 - l2) + (p2 - l2) ** 2)
    )
    return difference, lower, upper


def paired_bootstrap_interval(
    a: Sequence[float],
    b: Sequence[float],
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
    level: float = 0.95,
) -> tuple[float, float, float]:
    """(mean(b - a), lower, upper): the percentile bootstrap interval of the mean paired difference, the episodes
    resampled with replacement (the same episodes for both policies in each resample: `stats.bootstrap_mean_interval`
    of the per-episode differences)."""
    diffs = np.asarray(b, dtype=np.float64) - np.asarray(a, dtype=np.float64)  # (N,)
    if diffs.ndim != 1 or len(diffs) == 0:
        raise ValueError(f"paired_bootstrap_interval needs two aligned, non-empty lists, got {diffs.shape}")
    lower, upper = bootstrap_mean_interval(diffs, resamples, seed, level)
    return float(diffs.mean()), lower, upper
