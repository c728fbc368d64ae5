"""Honest statistics for trial outcomes: Wilson score intervals and per-group success tables."""

from __future__ import annotations

import math
import statistics
from collections import Counter, defaultdict
from typing import Iterable


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval for ``k`` successes in ``n`` trials (Wilson 1927); (0, 1) when n = 0.

    (p + z^2/2n +- z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n)
    """
    if not 0 <= k <= n:
        raise ValueError(f"need 0 <= k <= n, got k={k}, n={n}")
    if n == 0:
        return 0.0, 1.0
    p = k / n
    centre = p + z * z / (2 * n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    den = 1 + z * z / n
    lo = 0.0 if k == 0 else max(0.0, (centre - half) / den)  # exact ends: rounding once put 1 - 1e-16 above k = n
    return lo, 1.0 if k == n else min(1.0, (centre + half) / den)


def newcombe(k_a: int, n_a: int, k_b: int, n_b: int) -> tuple[float, float]:
    """95 % interval of the difference of two independent rates, ``k_b / n_b - k_a / n_a``, from their Wilson
    intervals (Newcombe 1998, method 10): d - sqrt((p_b - l_b)^2 + (u_a - p_a)^2), d + sqrt((u_b - p_b)^2 +
    (p_a - l_a)^2); (-1, 1) when a rate has no trials."""
    if not n_a or not n_b:
        return -1.0, 1.0
    pa, pb = k_a / n_a, k_b / n_b
    (la, ua), (lb, ub) = wilson(k_a, n_a), wilson(k_b, n_b)
    d = pb - pa
    return d - math.sqrt((pb - lb) ** 2 + (ua - pa) ** 2), d + math.sqrt((ub - pb) ** 2 + (pa - la) ** 2)


def rate_row(k: int, n: int) -> dict:
    """Successes, trials, rate and its Wilson 95 % interval."""
    lo, hi = wilson(k, n)
    return {"success": k, "n": n, "rate": k / n if n else float("nan"), "wilson95": [lo, hi]}


def summarise(records: Iterable[dict]) -> dict:
    """Success rate with its interval, per-block and per-failure tables, targets whose class perception got
    wrong, mean pose error and simulated time; for kitting and stack, the median final pose error of the
    placed block against the task's target."""
    recs = list(records)
    ok = [r["outcome"] == "success" for r in recs]
    by_block: dict[str, list[bool]] = defaultdict(list)
    for r, s in zip(recs, ok):
        by_block[(r.get("target") or {}).get("type", "(no block there)")].append(s)
    errs = [r["pose_error"]["err"] for r in recs if r.get("pose_error")]
    final = [r["final_error"] for r in recs if r.get("final_error")]
    extra = {"final_error": {"episodes": len(final),
                             "median_te_m": statistics.median(f["te"] for f in final),
                             "median_abs_yaw_deg": statistics.median(abs(f["yaw_deg"]) for f in final)}} if final else {}
    return {
        "episodes": len(recs),
        **rate_row(sum(ok), len(recs)),
        "grasp_success": rate_row(sum(bool(r.get("grasped")) for r in recs), len(recs)),
        "per_block": {b: rate_row(sum(v), len(v)) for b, v in sorted(by_block.items())},
        "failures": dict(sorted(Counter(r["failure"] for r in recs if r["failure"]).items())),
        "wrong_class": sum((r.get("target") or {}).get("class_ok") is False for r in recs),
        "mean_pose_error_m": sum(errs) / len(errs) if errs else None,
        "mean_sim_time_s": sum(r["sim_time"] for r in recs) / len(recs) if recs else None,
        **extra,
    }
