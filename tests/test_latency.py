"""Perception's latency per look: declared, the provider's own, or measured from a campaign's timings."""

import pytest

from posegrasp.grasping.latency import campaign_latency, looks, run_latency
from posegrasp.grasping.perception import NoisyOracleProvider, OracleProvider


class _Net:
    name = "net"  # a provider that declares no latency


def test_declared_wins_then_the_providers_own_then_the_measured_median():
    recs = [{"episode": 0, "attempts": [{}, {}, {}]}, {"episode": 1}, {"episode": 2, "attempts": []}]
    timings = {0: {"wall_s": {"perceive": 2.0}}, 1: {"wall_s": {"perceive": 0.25}}, 2: {"wall_s": {}}}
    assert [looks(r) for r in recs] == [4, 1, 1]
    assert campaign_latency(1.5, OracleProvider(), recs, timings) == {"seconds": 1.5, "how": "declared"}
    assert campaign_latency(None, NoisyOracleProvider(), recs, timings) == {"seconds": 0.0, "how": "provider"}
    assert campaign_latency(None, _Net(), recs, timings) == {"seconds": 0.25, "how": "measured"}  # of 0.5, 0.25, 0
    assert campaign_latency(None, _Net(), recs, {}) == {"seconds": 0.0, "how": "none"}


@pytest.mark.parametrize("text, seconds", [
    ('{"perception_latency": {"seconds": 0.3, "how": "measured"}}', 0.3),
    ('{"perception_latency": {"seconds": -1}}', 0.0), ('{}', 0.0), ('not json', 0.0)])
def test_a_runs_latency_comes_from_its_summary_or_is_zero(tmp_path, text, seconds):
    (tmp_path / "summary.json").write_text(text)
    assert run_latency(tmp_path) == seconds
    (tmp_path / "other").mkdir()
    assert run_latency(tmp_path / "other") == 0.0  # no summary.json
