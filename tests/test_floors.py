"""Success floors for short trial runs (``helpers.success_floor``) against scipy's binomial distribution."""

from __future__ import annotations

import pytest
from scipy.stats import binom

from helpers import success_floor
from posegrasp.grasping.stats import wilson


def test_floor_by_hand():
    # p = 0.96428 (Wilson lower end of 198/200): P(X < 8) = 0.45 %, P(X < 9) = 4.8 % over 10 episodes
    assert success_floor(198, 200, 10) == 8
    assert success_floor(200, 200, 1) == 0 and success_floor(0, 200, 5) == 0  # P(X < 1) = 1.9 % at p = 0.981


@pytest.mark.parametrize("k, n", [(198, 200), (196, 200), (194, 200), (150, 200), (29, 30)])
def test_floor_is_the_one_percent_binomial_quantile_at_the_wilson_lower_end(k, n):
    p = wilson(k, n)[0]
    for m in (1, 2, 5, 8, 10, 20, 50):
        f = success_floor(k, n, m)
        assert binom.cdf(f - 1, m, p) <= 0.01 < binom.cdf(f, m, p), (m, f)
