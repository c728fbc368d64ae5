"""The type check's candidates and choice (``perception.type_check``)."""

import numpy as np
import pytest

from posegrasp.errors import ConfigError
from posegrasp.perception.type_check import TypeCheckConfig, best_per_part, candidates, choose, cost


def test_candidates_are_the_likely_types_most_probable_first_and_never_not_a_block():
    ids = [0, 1, 2, 3, 4]
    prob = np.array([0.1, 0.04, 0.5, 0.3, 0.06])
    assert candidates(prob, ids, TypeCheckConfig()) == [(2, 0.5), (3, 0.3), (4, 0.06)]
    assert candidates(prob, ids, TypeCheckConfig(max_types=2)) == [(2, 0.5), (3, 0.3)]
    assert candidates(prob, ids, TypeCheckConfig(min_prob=0.4)) == [(2, 0.5)]
    assert candidates(prob, ids, TypeCheckConfig(weight=0.0)) == [(2, 0.5)]  # off: the classifier's arg-max
    assert candidates(np.array([0.5, 0.45, 0.05, 0.0, 0.0]), ids, TypeCheckConfig()) == [(0, 0.5)]
    assert candidates(np.array([0.02, 0.98]), [1, 2], TypeCheckConfig()) == [(2, pytest.approx(0.98))]


def test_choose_weighs_the_fit_against_the_classifier():
    cfg = TypeCheckConfig(weight=0.001)
    assert cost(0.5, cfg) == pytest.approx(0.001 * np.log(2.0)) and cost(1.0, cfg) == 0.0
    # costs: 0.004 - 0.001 ln 0.6 = 0.00451; 0.002 - 0.001 ln 0.4 = 0.00292
    assert choose([0.004, 0.002], [0.6, 0.4], cfg) == 1
    assert choose([0.0023, 0.002], [0.6, 0.4], cfg) == 0  # 0.00281 against 0.00292
    assert choose([0.0023, 0.002], [0.6, 0.4], TypeCheckConfig(weight=0.0)) == 1
    assert choose([0.002, 0.002], [0.5, 0.5], cfg) == 0  # ties: the first

    # parts 7 and 3, fitted as two types and one: each part's best, in the order the parts first appear
    assert best_per_part([7, 3, 7], [0.004, 0.009, 0.002], [0.6, 1.0, 0.4], cfg) == [2, 1]
    assert best_per_part([7, 3, 7], [0.004, 0.009, 0.002], [0.6, 1.0, 0.4], TypeCheckConfig(weight=1.0)) == [0, 1]


def test_settings_are_checked():
    with pytest.raises(ConfigError, match="max_types"):
        TypeCheckConfig(max_types=0)
    with pytest.raises(ConfigError, match="steps_margin"):
        TypeCheckConfig(steps_margin=-0.001)
