"""Bin picking's statistics: the campaign summary's ``bin_pick`` entries (``bin_metrics``), their terminal lines,
and the comparison of two runs on the same seeds (``compare``).

Per episode, percent cleared (mean, Student-t 95 % interval); per attempt, success (Wilson 95 %) and grasp success
(the attempts that went for a part: VGN's grasp success rate, where a look that finds no grasp is no grasp); picks
per hour of the cell's cycle time (the arm's simulated motion plus perception's latency at every look,
``grasping.latency``) and per simulated hour; attempt failures by reason, episode ends, success by part type and by
the target's visible fraction.

Two runs are judged as a cell is bought: by reliability first (attempt success; Fisher's exact test, Newcombe's
interval of the difference), then, where reliability does not differ at p < 0.05, by picks per hour (paired episode
by episode, Wilcoxon signed-rank). Percent cleared is reported beside them, never the verdict: a noisy estimator
that fails and tries again clears as much of a tote as an exact one, at a cost in cycle time.
"""

from __future__ import annotations

import math
import statistics
from collections import Counter, defaultdict

import numpy as np

from rich.console import Console

from posegrasp.grasping.latency import looks
from posegrasp.grasping.record import Failure
from posegrasp.grasping.stats import newcombe, rate_row
from posegrasp.grasping.tables import print_failures, rate_text
from posegrasp.grasping.tasks.bin_pick.config import BIN_PICK

#: Visible-fraction bins of the summary: (label, low, high), low <= fraction < high.
VISIBILITY_BINS = (("<0.5", 0.0, 0.5), ("0.5-0.9", 0.5, 0.9), (">=0.9", 0.9, math.inf))


def mean_ci95(values: list[float], lo: float = -math.inf, hi: float = math.inf) -> dict:
    """Mean of ``values`` with its Student-t 95 % interval, clipped to [``lo``, ``hi``] (None for fewer than 2
    values)."""
    n = len(values)
    if n == 0:
        return {"n": 0, "mean": None, "ci95": None}
    mean = statistics.fmean(values)
    if n < 2:
        return {"n": n, "mean": mean, "ci95": None}
    from scipy.stats import t

    half = float(t.ppf(0.975, n - 1)) * statistics.stdev(values) / math.sqrt(n)
    return {"n": n, "mean": mean, "ci95": [max(lo, mean - half), min(hi, mean + half)]}


def visibility_bin(fraction: float | None) -> str:
    """The ``VISIBILITY_BINS`` label of a visible fraction ("unknown": none measured)."""
    if fraction is None:
        return "unknown"
    return next(label for label, lo, hi in VISIBILITY_BINS if lo <= fraction < hi)


def grasped_for(attempt: dict) -> bool:
    """Did the attempt (its JSON record) go for a part with a grasp (or for a false detection): a target, and not a
    roll off a wall (``roll.py``: no grasp)?"""
    return bool(attempt.get("target")) and attempt.get("failure") != Failure.ROLLED


def cycle_hours(record: dict, latency: float) -> float:
    """An episode's cycle time (hours): the arm's simulated time plus ``latency`` seconds of perception per look."""
    return (record["sim_time"] + looks(record) * latency) / 3600.0


def bin_metrics(records: list[dict], latency: float = 0.0) -> dict:
    """Bin picking's summary entries over its episodes' JSON records and the campaign's perception ``latency``
    (s per look; ``BinPickTask.metrics``)."""
    from posegrasp.grasping.stats import rate_row

    eps = [r for r in records if r.get("task") == BIN_PICK]
    attempts = [a for r in eps for a in r.get("attempts", [])]
    ok = [a["outcome"] == "success" for a in attempts]
    went = [s for a, s in zip(attempts, ok) if grasped_for(a)]
    by_type: dict[str, list[bool]] = defaultdict(list)
    by_vis: dict[str, list[bool]] = defaultdict(list)
    for a, s in zip(attempts, ok):
        if grasped_for(a):
            by_type[a["target"].get("type", "(no part there)")].append(s)
            by_vis[visibility_bin(a.get("visib_fract"))].append(s)
    sim_hours = sum(r["sim_time"] for r in eps) / 3600.0
    hours = sum(cycle_hours(r, latency) for r in eps)
    labels = [label for label, _, _ in VISIBILITY_BINS] + ["unknown"]
    tray = tray_metrics(eps, latency)
    shakes = sum(bool(a.get("shaken")) for a in attempts)  # the tote's shakes (``shake.py``), none without a stage
    return {"bin_pick": {
        **({"tray": tray} if tray else {}),
        **({"shakes": shakes} if shakes else {}),
        "percent_cleared": mean_ci95([100.0 * r["cleared"] for r in eps], 0.0, 100.0),
        "episodes_cleared": sum(r["outcome"] == "success" for r in eps),
        "parts_present": sum(r["n_blocks"] for r in eps),
        "parts_removed": sum(r["removed"] for r in eps),
        "attempts": rate_row(sum(ok), len(ok)),
        "grasps": rate_row(sum(went), len(went)),
        "picks": sum(ok),
        "sim_hours": sim_hours,
        "picks_per_sim_hour": sum(ok) / sim_hours if sim_hours > 0 else None,
        "picks_per_hour": sum(ok) / hours if hours > 0 else None,  # the arm's time plus perception's latency
        "attempt_failures": dict(sorted(Counter(a["failure"] for a in attempts if a.get("failure")).items())),
        "episode_ends": dict(sorted(Counter(r["failure"] or "cleared" for r in eps).items())),
        "per_type": {t: rate_row(sum(v), len(v)) for t, v in sorted(by_type.items())},
        "per_visibility": {b: rate_row(sum(by_vis[b]), len(by_vis[b])) for b in labels if by_vis.get(b)},
    }}


def _spread(values: list[float]) -> dict:
    """Median, 90th percentile and largest of ``values`` (None each when there are none)."""
    if not values:
        return {"n": 0, "median": None, "p90": None, "max": None}
    v = np.asarray(values, float)
    return {"n": len(v), "median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "max": float(v.max())}


def tray_metrics(eps: list[dict], latency: float = 0.0) -> dict | None:
    """The tray's entries over bin-picking records that placed into it (None: none did): placement success per
    attempt (Wilson; an attempt succeeds when its part rests in its slot within the tolerances), parts placed per
    episode (mean, t interval) and per hour of cycle time, and the set-down parts' errors against their slots:
    position (mm, xy) and yaw (deg, its magnitude), modulo symmetries."""
    tray = [r for r in eps if r.get("place") == "tray"]
    if not tray:
        return None
    attempts = [a for r in tray for a in r.get("attempts", [])]
    errs = [a["place_error"] for a in attempts if a.get("place_error")]
    placed = [sum(a["outcome"] == "success" for a in r.get("attempts", [])) for r in tray]
    hours = sum(cycle_hours(r, latency) for r in tray)
    return {"placed": rate_row(sum(placed), len(attempts)),
            "placed_per_episode": mean_ci95([float(p) for p in placed], 0.0),
            "placed_per_hour": sum(placed) / hours if hours > 0 else None,
            "set_down": len(errs),
            "position_error_mm": _spread([1000.0 * e["te"] for e in errs]),
            "yaw_error_deg": _spread([abs(e["yaw_deg"]) for e in errs])}


def print_summary(b: dict, console: Console) -> None:
    """Bin picking's lines of the summary: percent cleared, attempt and grasp success, picks per hour, attempt
    failures."""
    pc = b["percent_cleared"]
    ci = f" (t 95 % interval {pc['ci95'][0]:.1f}-{pc['ci95'][1]:.1f} %)" if pc["ci95"] else ""
    mean = f"{pc['mean']:.1f} %" if pc["mean"] is not None else "-"
    pph = f"{b['picks_per_hour']:.0f}" if b.get("picks_per_hour") else "-"
    console.print(f"[bold]bin picking[/]: cleared {mean} of the parts per episode{ci}, "
                  f"{b['episodes_cleared']}/{pc['n']} totes emptied; attempts {rate_text(b['attempts'])}; grasps "
                  f"(attempts that went for a part) {rate_text(b['grasps'])}; {pph} picks per hour (arm and perception)"
                  + (f"; the tote shaken {b['shakes']} times" if b.get("shakes") else ""))
    t = b.get("tray")
    if t:
        pos, yaw = t["position_error_mm"], t["yaw_error_deg"]
        errs = (f"; of the {t['set_down']} set down, position error median {pos['median']:.1f} mm (90 % under "
                f"{pos['p90']:.1f}), yaw error median {yaw['median']:.1f} deg (90 % under {yaw['p90']:.1f})"
                if t["set_down"] else "")
        console.print(f"[bold]tray[/]: placed {rate_text(t['placed'])} of the attempts, "
                      f"{t['placed_per_episode']['mean']:.1f} parts per episode{errs}")
    print_failures(b["attempt_failures"], "failed attempts", console)


def compare(a: dict[int, dict], b: dict[int, dict], common: list[int],
            latency: tuple[float, float] = (0.0, 0.0)) -> dict:
    """Two bin-picking runs on their common episodes (``latency``: each run's perception seconds per look):
    reliability (attempt success: each run's Wilson 95 % interval, the difference B - A with Newcombe's 95 %
    interval, Fisher's exact test), picks per hour of cycle time paired episode by episode (mean difference B - A,
    Wilcoxon signed-rank), grasp success and percent cleared (paired, Wilcoxon) as figures, and the verdict
    (``verdict``)."""
    from scipy.stats import fisher_exact

    runs = [[t for i in common for t in run[i].get("attempts", [])] for run in (a, b)]
    attempts = unpaired_rates(runs)
    ra, rb = attempts["a"], attempts["b"]
    attempts["fisher_p"] = float(fisher_exact([[ra["success"], ra["n"] - ra["success"]],
                                               [rb["success"], rb["n"] - rb["success"]]]).pvalue)
    rates = [[_picks(run[i]) / max(cycle_hours(run[i], s), 1e-12) for i in common] for run, s in zip((a, b), latency)]
    result = {
        "attempts": attempts,
        "picks_per_hour": _paired(*rates),
        "latency_s": list(latency),
        "grasps": unpaired_rates([[t for t in run if grasped_for(t)] for run in runs]),
        "percent_cleared": _paired([100.0 * a[i]["cleared"] for i in common], [100.0 * b[i]["cleared"] for i in common]),
    }
    if any(run[i].get("place") == "tray" for run in (a, b) for i in common):
        result["tray_position_error_mm"] = _paired(*[[_mean_place_error(run[i]) for i in common] for run in (a, b)])
    return {**result, **verdict(result)}


def _mean_place_error(record: dict) -> float:
    """An episode's mean position error (mm) of the parts it set down in the tray (0 when none)."""
    errs = [1000.0 * t["place_error"]["te"] for t in record.get("attempts", []) if t.get("place_error")]
    return sum(errs) / len(errs) if errs else 0.0


def _picks(record: dict) -> int:
    return sum(t["outcome"] == "success" for t in record.get("attempts", []))


def _paired(xa: list[float], xb: list[float]) -> dict:
    """Per-episode values of runs A and B: their means, the mean difference B - A, the episodes each was better in,
    and the two-sided Wilcoxon signed-rank p (1 when no episode differs)."""
    from scipy.stats import wilcoxon

    diffs = [y - x for x, y in zip(xa, xb)]
    p = float(wilcoxon(xb, xa).pvalue) if any(diffs) else 1.0
    return {"a_mean": sum(xa) / len(xa), "b_mean": sum(xb) / len(xb), "difference": sum(diffs) / len(diffs),
            "b_better": sum(d > 0 for d in diffs), "a_better": sum(d < 0 for d in diffs), "wilcoxon_p": p}


#: The significance level of the verdict's tests.
VERDICT_ALPHA = 0.05


def verdict(r: dict) -> dict:
    """Which run is better and by what: reliability (attempt success, Fisher's p < ``VERDICT_ALPHA``), else picks
    per hour (Wilcoxon's p < ``VERDICT_ALPHA``), else neither; ``judged_by`` the deciding figure (reliability when
    neither decides) with its difference B - A and p-value."""
    rel, pph = r["attempts"], r["picks_per_hour"]
    if rel["fisher_p"] < VERDICT_ALPHA and rel["difference"] != 0:
        key, diff, p = "reliability", rel["difference"], rel["fisher_p"]
    elif pph["wilcoxon_p"] < VERDICT_ALPHA and pph["difference"] != 0:
        key, diff, p = "picks_per_hour", pph["difference"], pph["wilcoxon_p"]
    else:
        return {"better": "neither", "decided_by": None, "judged_by": [rel["difference"], rel["fisher_p"]]}
    return {"better": "B" if diff > 0 else "A", "decided_by": key, "judged_by": [diff, p]}


def unpaired_rates(attempts: list[list[dict]]) -> dict:
    """Two runs' attempts (JSON records): each run's success (``rate_row``) and the difference B - A with
    Newcombe's 95 % interval."""
    ra, rb = (rate_row(sum(t["outcome"] == "success" for t in run), len(run)) for run in attempts)
    return {"a": ra, "b": rb, "difference": (rb["rate"] if rb["n"] else 0.0) - (ra["rate"] if ra["n"] else 0.0),
            "difference_ci95": list(newcombe(ra["success"], ra["n"], rb["success"], rb["n"]))}


def print_comparison(r: dict, console: Console) -> None:
    t = r["attempts"]
    lo, hi = t["difference_ci95"]
    console.print(f"reliability (attempt success): A {t['a']['success']}/{t['a']['n']}, B {t['b']['success']}/"
                  f"{t['b']['n']}, B - A {100 * t['difference']:+.1f} points (Newcombe 95 % {100 * lo:+.1f} to "
                  f"{100 * hi:+.1f}); Fisher exact p = {t['fisher_p']:.4g}")
    p, (la, lb) = r["picks_per_hour"], r["latency_s"]
    console.print(f"picks per hour (arm and perception, {la:g} s and {lb:g} s a look): A {p['a_mean']:.0f}, B "
                  f"{p['b_mean']:.0f}, B - A {p['difference']:+.0f} (B better in {p['b_better']} episodes, A in "
                  f"{p['a_better']}); Wilcoxon signed-rank p = {p['wilcoxon_p']:.4g}")
    g = r["grasps"]
    console.print(f"grasp success (attempts that went for a part): A {g['a']['success']}/{g['a']['n']}, B "
                  f"{g['b']['success']}/{g['b']['n']}")
    c = r["percent_cleared"]
    console.print(f"percent cleared (a figure, not the verdict): A {c['a_mean']:.1f} %, B {c['b_mean']:.1f} %")
    e = r.get("tray_position_error_mm")
    if e:
        console.print(f"tray: mean position error per episode A {e['a_mean']:.2f} mm, B {e['b_mean']:.2f} mm "
                      f"(Wilcoxon signed-rank p = {e['wilcoxon_p']:.4g}); reliability is placement success")
    if r["better"] == "neither":
        console.print(f"better: neither (no difference in reliability or picks per hour at p < {VERDICT_ALPHA})")
    else:
        what = {"reliability": "more reliable", "picks_per_hour": "as reliable, more picks per hour"}[r["decided_by"]]
        console.print(f"better: {r['better']} ({what}; p = {r['judged_by'][1]:.4g})")
