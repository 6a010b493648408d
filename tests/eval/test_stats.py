"""The 95 % intervals of rollout/stats.py against values computed by hand, and the one printed form."""

from __future__ import annotations

import pytest

from openfly_agent.rollout.stats import bootstrap_mean_interval, format_interval, wilson_interval


def test_wilson_interval_of_hand_computed_rates():
    # z = 1.959964, z^2 = 3.841459.
    # 20 of 89: p = 0.224719, z^2/n = 0.043163, centre = (p + z^2/2n) / (1 + z^2/n) = 0.246300 / 1.043163
    # = 0.236109; half = z sqrt(p(1-p)/n + z^2/4n^2) / (1 + z^2/n) = 1.959964 * sqrt(0.0019575 + 0.0001212)
    # / 1.043163 = 0.085665 -> 0.150444 .. 0.321774.
    assert wilson_interval(20, 89) == pytest.approx((0.150444, 0.321774), abs=2e-6)
    # 0 of 260: centre = half = (z^2/2n) / (1 + z^2/n), so low = 0 and high = z^2 / (n + z^2)
    # = 3.841459 / 263.841459 = 0.014560.
    assert wilson_interval(0, 260) == pytest.approx((0.0, 0.014560), abs=2e-6)
    # 260 of 260 mirrors it: low = n / (n + z^2) = 260 / 263.841459 = 0.985440, high = 1.
    assert wilson_interval(260, 260) == pytest.approx((0.985440, 1.0), abs=2e-6)
    # 1 of 6: centre = (0.166667 + 0.320122) / 1.640243 = 0.296779; half = 1.959964 * sqrt(0.0231481
    # + 0.0266760) / 1.640243 = 0.266725 -> 0.030054 .. 0.563504.
    assert wilson_interval(1, 6) == pytest.approx((0.030054, 0.563504), abs=2e-6)


def test_wilson_interval_refuses_impossible_counts():
    with pytest.raises(ValueError, match="trials >= 1"):
        wilson_interval(0, 0)
    with pytest.raises(ValueError, match="outside 0..5"):
        wilson_interval(6, 5)


def test_bootstrap_interval_of_hand_known_cases():
    # Constant values: every resample has the same mean.
    assert bootstrap_mean_interval([3.5] * 7) == pytest.approx((3.5, 3.5))
    # Two values 0 and 1: a resample's mean is 0, 0.5 or 1 with probabilities 1/4, 1/2, 1/4, so the 2.5 %
    # quantile is 0 and the 97.5 % one is 1.
    assert bootstrap_mean_interval([0.0, 1.0]) == (0.0, 1.0)
    # 100 ones in 400: close to the normal interval 0.25 +- 1.96 sqrt(0.25 * 0.75 / 400) = 0.2076 .. 0.2924.
    low, high = bootstrap_mean_interval([1.0] * 100 + [0.0] * 300)
    assert low == pytest.approx(0.2076, abs=0.005) and high == pytest.approx(0.2924, abs=0.005)


def test_bootstrap_interval_is_fixed_by_its_seed():
    values = [(0.37 * i) % 1.0 for i in range(30)]
    first = bootstrap_mean_interval(values)
    assert bootstrap_mean_interval(list(values)) == first  # the default seed: the same numbers every time
    assert bootstrap_mean_interval(values[::-1]) == first  # ... in any order of the episodes
    assert bootstrap_mean_interval(values, seed=1) != first
    assert first[0] <= sum(values) / len(values) <= first[1]
    with pytest.raises(ValueError, match="non-empty"):
        bootstrap_mean_interval([])


def test_format_interval_is_the_one_table_form():
    assert format_interval(29.21, (20.94, 39.06)) == "29.2 (20.9-39.1)"
    assert format_interval(0.0, (0.0, 1.456)) == "0.0 (0.0-1.5)"
    assert format_interval(12.345, None, decimals=2) == "12.35"
