"""``posegrasp compare RUN_A RUN_B``: did a perception change make grasping better or worse?

Two trial runs on the same episode seeds are paired episode by episode, whatever their perception providers
(oracle, model, a plug-in, a replayed BOP results file). Reported: each run's success rate with
its Wilson 95 % interval, the difference, McNemar's exact test on the discordant pairs (b = A succeeded and B
failed, c = A failed and B succeeded; two-sided p = min(1, 2 P[X <= min(b, c)]) with X ~ Binomial(b + c, 1/2)),
per-block differences and the episodes that flipped. A task adds its own comparison and says what judges it
(``Task.compare``, ``Task.judged_by``): bin picking is judged by reliability (attempt success, Fisher's exact test),
then picks per hour of cycle time with each run's perception latency, with percent cleared as a figure.
``--fail-if-worse`` makes the exit status 1 when B is worse than A with p < alpha by that judgement, for CI.
"""

from __future__ import annotations

import argparse
import math
import os
from collections import defaultdict
from pathlib import Path

from rich.console import Console
from rich.table import Table

from posegrasp.arguments import number, out_file
from posegrasp.errors import DatasetError, UserError
from posegrasp.grasping.latency import run_latency
from posegrasp.grasping.runfolder import CAMPAIGN, EPISODES, read_campaign, read_episodes
from posegrasp.grasping.stats import rate_row
from posegrasp.grasping.tasks import get_task
from posegrasp.io import write_json
from posegrasp.outputs import check_out_file, mark_json


def mcnemar_exact(b: int, c: int) -> float:
    """Two-sided exact McNemar p-value for ``b`` and ``c`` discordant pairs (1.0 when there are none)."""
    if b < 0 or c < 0:
        raise ValueError(f"discordant counts must be >= 0, got b={b}, c={c}")
    n = b + c
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(min(b, c) + 1)) / 2.0**n
    return min(1.0, 2.0 * tail)


def _success(rec: dict) -> bool:
    return rec["outcome"] == "success"


def load_run(path: str | Path) -> dict[int, dict]:
    """Episode records of a trial run folder (or its episodes.jsonl), by episode index; DatasetError if none."""
    p = Path(path)
    f = p / EPISODES if p.is_dir() else p
    recs = {i: raw for i, (raw, _) in read_episodes(f).items()}  # each record checked, as a resume checks it
    if not recs:
        raise DatasetError(f"{path} holds no trial episodes (expected {EPISODES} written by 'posegrasp trials')")
    gaps = sorted(set(range(max(recs) + 1)) - set(recs))
    if gaps:
        raise DatasetError(f"{path} lacks episode {gaps[0]} of 0..{max(recs)} ({len(gaps)} missing): run its trials "
                           "command again to complete it")
    return recs


def run_objects(path: str | Path) -> dict | None:
    """The object set a trial run folder (or its episodes.jsonl) ran on (``catalog.set_record``, from its
    campaign.json); None when there is no campaign.json beside the episodes."""
    p = Path(path)
    folder = p if p.is_dir() else p.parent
    return read_campaign(folder).set_record() if os.path.lexists(folder / CAMPAIGN) else None


def check_same_objects(path_a: str | Path, path_b: str | Path) -> None:
    """UserError when the two runs ran on different object sets (their set files' sha256 differ)."""
    sa, sb = run_objects(path_a), run_objects(path_b)
    if sa and sb and sa["sha256"] != sb["sha256"]:
        raise UserError(f"run A ran on the object set {sa['name']} ({sa['path']}) and run B on {sb['name']} "
                        f"({sb['path']}): compare runs on the same --objects")


def compare_runs(a: dict[int, dict], b: dict[int, dict], latency: tuple[float, float] = (0.0, 0.0)) -> dict:
    """Paired comparison of two runs on their common episodes (the same seeds in both); ``latency``: each run's
    perception seconds per look (``grasping.latency``), which a task judging throughput counts."""
    common = sorted(set(a) & set(b))
    if not common:
        raise UserError("the two runs share no episodes; run both with the same --seed and --episodes")
    ta, tb = (run[common[0]].get("task") or "pick-place" for run in (a, b))
    if ta != tb:
        raise UserError(f"run A is a {ta} run and run B a {tb} run: compare runs of the same --task")
    bad = [i for i in common if a[i].get("seed") != b[i].get("seed")]
    if bad:
        raise UserError(f"episode {bad[0]} has different seeds in the two runs; compare runs made with the same --seed")
    sa = [_success(a[i]) for i in common]
    sb = [_success(b[i]) for i in common]
    only_a = [i for i, x, y in zip(common, sa, sb) if x and not y]
    only_b = [i for i, x, y in zip(common, sa, sb) if y and not x]
    blocks: dict[str, list[tuple[bool, bool]]] = defaultdict(list)
    for i, x, y in zip(common, sa, sb):
        blocks[target_label(a[i].get("target"))].append((x, y))
    n = len(common)
    return {
        **get_task(ta).compare(a, b, common, latency),
        "task": ta,
        "episodes": n,
        "a": {"perception": a[common[0]].get("perception"), **rate_row(sum(sa), n)},  # any providers pair up
        "b": {"perception": b[common[0]].get("perception"), **rate_row(sum(sb), n)},
        "difference": (sum(sb) - sum(sa)) / n,
        "mcnemar": {"a_only": len(only_a), "b_only": len(only_b), "p_value": mcnemar_exact(len(only_a), len(only_b))},
        "per_block": {k: {"n": len(v), "a": sum(x for x, _ in v), "b": sum(y for _, y in v),
                          "difference": (sum(y for _, y in v) - sum(x for x, _ in v)) / len(v)}
                      for k, v in sorted(blocks.items())},
        "flipped": {"a_success_b_failure": [{"episode": i, "b_failure": b[i].get("failure")} for i in only_a],
                    "a_failure_b_success": [{"episode": i, "a_failure": a[i].get("failure")} for i in only_b]},
    }


def target_label(target: dict | None) -> str:
    """The per-block label of an episode's ``target`` (JSON): its type, a false detection's "(no block there)",
    or "(no target)" when the robot chose none (nothing seen, or no reachable grasp)."""
    if target is None:
        return "(no target)"
    return target.get("type", "(no block there)")


def is_worse(result: dict, alpha: float) -> bool:
    """B is significantly worse than A by what the task judges (``Task.judged_by``: the success rate and McNemar's
    p for the table tasks, percent cleared and Wilcoxon's p for bin picking): a negative difference, p < ``alpha``."""
    difference, p = get_task(result["task"]).judged_by(result)
    return difference < 0 and p < alpha


def print_comparison(result: dict, names: tuple[str, str], console: Console) -> None:
    t = Table(title=f"{result['episodes']} paired {result.get('task', 'pick-place')} episodes")
    for col in ("run", "perception", "success", "rate", "Wilson 95 %"):
        t.add_column(col)
    for key, name in zip(("a", "b"), names):
        r = result[key]
        t.add_row(name, str(r.get("perception")), f"{r['success']}/{r['n']}", f"{100 * r['rate']:.1f} %",
                  f"[{100 * r['wilson95'][0]:.1f}, {100 * r['wilson95'][1]:.1f}]")
    console.print(t)
    m = result["mcnemar"]
    console.print(f"difference B - A: {100 * result['difference']:+.1f} points; McNemar exact: "
                  f"A-only {m['a_only']}, B-only {m['b_only']}, p = {m['p_value']:.4g}")
    get_task(result["task"]).print_comparison(result, console)
    for key, label in (("a_success_b_failure", "A succeeded, B failed"), ("a_failure_b_success", "A failed, B succeeded")):
        eps = result["flipped"][key]
        if eps:
            console.print(f"{label}: " + ", ".join(str(e["episode"]) for e in eps))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compare", help="compare two trial runs on the same seeds (Wilson intervals, McNemar)")
    p.add_argument("run_a", help="baseline trial run folder")
    p.add_argument("run_b", help="candidate trial run folder")
    p.add_argument("--fail-if-worse", action="store_true", help="exit 1 if B is significantly worse than A")
    p.add_argument("--alpha", type=number("--alpha", 0, 1, open_lo=True, open_hi=True), default=0.05,
                   help="significance level for --fail-if-worse")
    p.add_argument("--out", type=out_file("--out", (".json",)), default=None, help="also write the comparison as JSON here")
    p.add_argument("--force", action="store_true", help="replace --out even if this command did not write it")
    p.set_defaults(run=run_compare)


def run_compare(args: argparse.Namespace) -> int:
    if args.out:
        check_out_file(args.out, "compare", [args.run_a, args.run_b], args.force)
    a, b = load_run(args.run_a), load_run(args.run_b)
    check_same_objects(args.run_a, args.run_b)
    result = compare_runs(a, b, (run_latency(args.run_a), run_latency(args.run_b)))
    print_comparison(result, (f"A {args.run_a}", f"B {args.run_b}"), Console())
    if args.out:
        write_json(args.out, mark_json(result, "compare"))
    if args.fail_if_worse and is_worse(result, args.alpha):
        print(f"B is worse than A (p = {get_task(result['task']).judged_by(result)[1]:.4g} < {args.alpha})")
        return 1
    return 0
