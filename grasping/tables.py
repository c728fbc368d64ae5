"""The terminal tables (rich) of a campaign's summary and of a comparison of two runs, as the table tasks show
them (``tasks.base.Task.print_summary``, ``Task.print_comparison``); a task with statistics of its own prints
those instead (bin picking: ``tasks.bin_pick.metrics``)."""

from __future__ import annotations

from rich.console import Console
from rich.table import Table

from posegrasp.grasping.record import Failure


def print_episodes(s: dict, console: Console) -> None:
    lo, hi = s["wilson95"]
    objects = s.get("objects", {}).get("name", "blocks")
    console.print(f"[bold]{s.get('task', 'pick-place')}, {s['perception']}, {objects}[/]: "
                  f"{s['success']}/{s['n']} episodes succeeded = "
                  f"{100 * s['rate']:.1f} % (Wilson 95 % interval {100 * lo:.1f}-{100 * hi:.1f} %); "
                  f"grasped {s['grasp_success']['success']}/{s['n']}; "
                  f"target of the wrong class {s.get('wrong_class', 0)}/{s['n']}")
    t = Table(title="per target block")
    for col in ("block", "success", "n", "rate", "95 % interval"):
        t.add_column(col)
    for b, row in s["per_block"].items():
        t.add_row(b, str(row["success"]), str(row["n"]), f"{100 * row['rate']:.1f} %",
                  f"{100 * row['wilson95'][0]:.1f}-{100 * row['wilson95'][1]:.1f} %")
    console.print(t)
    print_failures(s["failures"], "failures", console)


def print_failures(counts: dict[str, int], title: str, console: Console) -> None:
    f = Table(title=title)
    f.add_column("reason")
    f.add_column("count")
    for reason in Failure:
        if counts.get(reason):
            f.add_row(reason, str(counts[reason]))
    console.print(f)


def rate_text(r: dict) -> str:
    """``rate_row``'s row as "k/n succeeded = p % (Wilson 95 % lo-hi %)"."""
    if not r["n"]:
        return "0/0 succeeded"
    return (f"{r['success']}/{r['n']} succeeded = {100 * r['rate']:.1f} % "
            f"(Wilson 95 % {100 * r['wilson95'][0]:.1f}-{100 * r['wilson95'][1]:.1f} %)")


def print_per_block(result: dict, console: Console) -> None:
    """A comparison's success per target block type (``compare.compare_runs``' ``per_block``)."""
    pb = Table(title="per block (target type)")
    for col in ("block", "n", "A", "B", "B - A"):
        pb.add_column(col)
    for k, v in result["per_block"].items():
        pb.add_row(k, str(v["n"]), str(v["a"]), str(v["b"]), f"{100 * v['difference']:+.0f}")
    console.print(pb)
