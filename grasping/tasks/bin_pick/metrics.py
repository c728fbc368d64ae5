"""Bin picking's statistics: the campaign summary's ``bin_pick`` entries (``bin_metrics``), their terminal lines,
and the comparison of two runs on the same seeds (``compare``).

Per episode, percent cleared (mean, Student-t 95 % interval); per attempt, success (Wilson 95 %) and grasp success
(the attempts that went for a part: VGN's grasp success rate, where a look that finds no grasp is no grasp); picks
per simulated hour; attempt failures by reason, episode ends, success by part type and by the target's visible
fraction. Two runs: percent cleared paired episode by episode (Wilcoxon signed-rank), attempt and grasp success
unpaired (Newcombe's interval of the difference).
"""

from __future__ import annotations

import math
import statistics
from collections import Counter, defaultdict

from rich.console import Console

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


def bin_metrics(records: list[dict]) -> dict:
    """Bin picking's summary entries over its episodes' JSON records (``BinPickTask.metrics``)."""
    from posegrasp.grasping.stats import rate_row

    eps = [r for r in records if r.get("task") == BIN_PICK]
    attempts = [a for r in eps for a in r.get("attempts", [])]
    ok = [a["outcome"] == "success" for a in attempts]
    went = [s for a, s in zip(attempts, ok) if a.get("target")]  # the robot went for a part (or a false detection)
    by_type: dict[str, list[bool]] = defaultdict(list)
    by_vis: dict[str, list[bool]] = defaultdict(list)
    for a, s in zip(attempts, ok):
        if a.get("target"):
            by_type[a["target"].get("type", "(no part there)")].append(s)
            by_vis[visibility_bin(a.get("visib_fract"))].append(s)
    sim_hours = sum(r["sim_time"] for r in eps) / 3600.0
    labels = [label for label, _, _ in VISIBILITY_BINS] + ["unknown"]
    return {"bin_pick": {
        "percent_cleared": mean_ci95([100.0 * r["cleared"] for r in eps], 0.0, 100.0),
        "episodes_cleared": sum(r["outcome"] == "success" for r in eps),
        "parts_present": sum(r["n_blocks"] for r in eps),
        "parts_removed": sum(r["removed"] for r in eps),
        "attempts": rate_row(sum(ok), len(ok)),
        "grasps": rate_row(sum(went), len(went)),
        "picks": sum(ok),
        "sim_hours": sim_hours,
        "picks_per_sim_hour": sum(ok) / sim_hours if sim_hours > 0 else None,
        "attempt_failures": dict(sorted(Counter(a["failure"] for a in attempts if a.get("failure")).items())),
        "episode_ends": dict(sorted(Counter(r["failure"] or "cleared" for r in eps).items())),
        "per_type": {t: rate_row(sum(v), len(v)) for t, v in sorted(by_type.items())},
        "per_visibility": {b: rate_row(sum(by_vis[b]), len(by_vis[b])) for b in labels if by_vis.get(b)},
    }}


def print_summary(b: dict, console: Console) -> None:
    """Bin picking's lines of the summary: percent cleared, attempt and grasp success, picks per hour, attempt
    failures."""
    pc = b["percent_cleared"]
    ci = f" (t 95 % interval {pc['ci95'][0]:.1f}-{pc['ci95'][1]:.1f} %)" if pc["ci95"] else ""
    mean = f"{pc['mean']:.1f} %" if pc["mean"] is not None else "-"
    pph = f"{b['picks_per_sim_hour']:.0f}" if b["picks_per_sim_hour"] else "-"
    console.print(f"[bold]bin picking[/]: cleared {mean} of the parts per episode{ci}, "
                  f"{b['episodes_cleared']}/{pc['n']} totes emptied; attempts {rate_text(b['attempts'])}; grasps "
                  f"(attempts that went for a part) {rate_text(b['grasps'])}; {pph} picks per simulated hour")
    print_failures(b["attempt_failures"], "failed attempts", console)


def compare(a: dict[int, dict], b: dict[int, dict], common: list[int]) -> dict:
    """Two bin-picking runs on their common episodes: percent cleared paired episode by episode (mean difference
    B - A in points, Wilcoxon signed-rank test, two-sided; p = 1 when no episode differs), attempt success and grasp
    success (the attempts that went for a part; each run's Wilson 95 % interval, the difference B - A with
    Newcombe's 95 % interval; attempts differ in number and are not paired)."""
    from scipy.stats import wilcoxon

    ca = [100.0 * a[i]["cleared"] for i in common]
    cb = [100.0 * b[i]["cleared"] for i in common]
    diffs = [y - x for x, y in zip(ca, cb)]
    p = float(wilcoxon(cb, ca).pvalue) if any(diffs) else 1.0
    mean = sum(diffs) / len(diffs)
    return {
        "percent_cleared": {"a_mean": sum(ca) / len(ca), "b_mean": sum(cb) / len(cb), "difference": mean,
                            "b_better": sum(d > 0 for d in diffs), "a_better": sum(d < 0 for d in diffs),
                            "wilcoxon_p": p},
        "attempts": unpaired_rates([[t for i in common for t in run[i].get("attempts", [])] for run in (a, b)]),
        "grasps": unpaired_rates([[t for i in common for t in run[i].get("attempts", []) if t.get("target")]
                             for run in (a, b)]),
        "better": "B" if mean > 0 else "A" if mean < 0 else "neither",
    }


def unpaired_rates(attempts: list[list[dict]]) -> dict:
    """Two runs' attempts (JSON records): each run's success (``rate_row``) and the difference B - A with
    Newcombe's 95 % interval."""
    ra, rb = (rate_row(sum(t["outcome"] == "success" for t in run), len(run)) for run in attempts)
    return {"a": ra, "b": rb, "difference": (rb["rate"] if rb["n"] else 0.0) - (ra["rate"] if ra["n"] else 0.0),
            "difference_ci95": list(newcombe(ra["success"], ra["n"], rb["success"], rb["n"]))}


def print_comparison(r: dict, console: Console) -> None:
    c = r["percent_cleared"]
    console.print(f"percent cleared: A {c['a_mean']:.1f} %, B {c['b_mean']:.1f} %, B - A {c['difference']:+.1f} points "
                  f"(B better in {c['b_better']} episodes, A in {c['a_better']}); Wilcoxon signed-rank p = "
                  f"{c['wilcoxon_p']:.4g}")
    for key, label in (("attempts", "attempt success"), ("grasps", "grasp success (attempts that went for a part)")):
        t = r[key]
        lo, hi = t["difference_ci95"]
        console.print(f"{label}: A {t['a']['success']}/{t['a']['n']}, B {t['b']['success']}/{t['b']['n']}, "
                      f"B - A {100 * t['difference']:+.1f} points (Newcombe 95 % {100 * lo:+.1f} to {100 * hi:+.1f})")
    sure = "significant at p < 0.05" if c["wilcoxon_p"] < 0.05 else "not significant (p >= 0.05)"
    console.print(f"better at clearing the tote: {r['better']} ({sure})")
