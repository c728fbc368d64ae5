"""``posegrasp compare``: statistics against hand-computed cases, pairing and CI exit status."""

from __future__ import annotations

import json

import pytest

from helpers import run_cli
from posegrasp.grasping.compare import compare_runs, is_worse, mcnemar_exact
from posegrasp.grasping.stats import wilson


def test_mcnemar_exact_hand_computed():
    assert mcnemar_exact(0, 0) == 1.0
    assert mcnemar_exact(1, 6) == pytest.approx(2 * (1 + 7) / 2**7)  # 0.125
    assert mcnemar_exact(0, 10) == pytest.approx(2 / 2**10)  # 0.001953125
    assert mcnemar_exact(5, 5) == 1.0
    assert mcnemar_exact(2, 8) == pytest.approx(2 * (1 + 10 + 45) / 1024)  # 0.109375


def test_wilson_hand_computed():
    lo, hi = wilson(9, 10)
    assert (lo, hi) == pytest.approx((0.59585, 0.98212), abs=1e-4)
    assert wilson(0, 10)[0] == 0.0 and wilson(10, 10)[1] == pytest.approx(1.0)
    assert all(wilson(n, n)[1] == 1.0 and wilson(0, n)[0] == 0.0 for n in range(1, 300))  # exact: k/n - lo, hi - k/n >= 0


def _runs(a_ok: list[bool], b_ok: list[bool]) -> tuple[dict, dict]:
    def rec(i, ok):
        return {"episode": i, "seed": 100 + i, "outcome": "success" if ok else "failure",
                "failure": None if ok else "pose error", "target": {"type": "cube" if i % 2 else "arch"}}
    return ({i: rec(i, x) for i, x in enumerate(a_ok)}, {i: rec(i, y) for i, y in enumerate(b_ok)})


def test_compare_counts_flips_and_blocks():
    a, b = _runs([True] * 10 + [False, True], [True] * 2 + [False] * 8 + [True, True])
    r = compare_runs(a, b)
    assert r["episodes"] == 12 and r["a"]["success"] == 11 and r["b"]["success"] == 4
    assert r["mcnemar"]["a_only"] == 8 and r["mcnemar"]["b_only"] == 1
    assert r["mcnemar"]["p_value"] == pytest.approx(2 * (1 + 9) / 2**9)
    assert [e["episode"] for e in r["flipped"]["a_failure_b_success"]] == [10]
    assert r["per_block"]["arch"]["n"] == 6 and r["difference"] == pytest.approx(-7 / 12)
    assert is_worse(r, 0.05) and not is_worse(compare_runs(a, a), 0.05)


def test_mismatched_seeds_are_refused():
    from posegrasp.errors import UserError

    a, b = _runs([True, False], [True, True])
    b[1]["seed"] = 999
    with pytest.raises(UserError, match="different seeds"):
        compare_runs(a, b)


@pytest.mark.slow
def test_cli_fail_if_worse(tmp_path):
    a, b = _runs([True] * 12, [True] * 2 + [False] * 10)
    for name, recs in (("A", a), ("B", b)):
        (tmp_path / name).mkdir()
        full = ({**r, "scene_seed": 0, "n_blocks": 1, "perception": "oracle", "target": None} for r in recs.values())
        (tmp_path / name / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in full))
    assert run_cli("compare", str(tmp_path / "A"), str(tmp_path / "B")).returncode == 0
    r = run_cli("compare", str(tmp_path / "A"), str(tmp_path / "B"), "--fail-if-worse")
    assert r.returncode == 1 and "worse" in r.stdout
    r = run_cli("compare", str(tmp_path / "A"), str(tmp_path / "missing"))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
