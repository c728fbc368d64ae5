"""The bin-picking ``Task``: its scene, records, looks and checks, and what its summary, comparison and report
show (``metrics``, ``report``)."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
from rich.console import Console

from posegrasp.errors import ConfigError, UserError
from posegrasp.grasping.tables import print_failures
from posegrasp.grasping.tasks.base import Graspable, Task, task_types
from posegrasp.grasping.tasks.bin_pick import metrics
from posegrasp.grasping.tasks.bin_pick.config import BIN_PICK, HELD_LOOK
from posegrasp.grasping.tasks.bin_pick.record import BinPickRecord
from posegrasp.grasping.tasks.bin_pick.scene import bin_scene, check_outbox, tray_of
from posegrasp.sim.clutter import CLUTTER_KINDS, ClutterConfig, check_clutter
from posegrasp.sim.workcell import Workcell

if TYPE_CHECKING:
    from posegrasp.executor import Executor
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping.episode import Episode
    from posegrasp.grasping.report.run import TrialRun

#: The ``im_id`` of every look into the tote a bin-picking episode may take: one per attempt, at most twice the most
#: parts; and of the second looks at held parts (a tray's ``second_look``), ``HELD_LOOK`` + the attempt.
BIN_LOOKS = tuple(range(2 * int(ClutterConfig.__dataclass_fields__["max_parts"].metadata["range"][1])))
HELD_LOOKS = tuple(HELD_LOOK + a for a in BIN_LOOKS)


class BinPickTask(Task):
    """Empty a tote (or a pile) into the out-box, attempt after attempt (a ``Task``; the module docstring)."""

    name = BIN_PICK
    looks = BIN_LOOKS + HELD_LOOKS
    record_type = BinPickRecord
    suction = True
    fixed_looks = BIN_LOOKS[:1]  # the first look only: the later ones follow the picks

    def blocks(self, cfg: TrialConfig) -> tuple[int, int]:
        """``bin_pick.clutter.parts``."""
        lo, hi = cfg.bin_pick.clutter.parts
        return lo, hi

    def with_scene(self, cfg: TrialConfig, scene: str | None, blocks: int | None) -> TrialConfig:
        """``cfg`` with ``--scene`` (bin or pile; None: ``bin_pick.scene``) and ``--blocks`` (parts per episode)."""
        if scene == "table":
            raise UserError("--task bin-pick empties a tote or a heap: use --scene bin or --scene pile, not table")
        b = cfg.bin_pick
        clutter = dataclasses.replace(b.clutter, parts=(blocks, blocks)) if blocks else b.clutter
        return dataclasses.replace(cfg, bin_pick=dataclasses.replace(b, scene=scene or b.scene, clutter=clutter))

    def check(self, cfg: TrialConfig) -> None:
        """A one-line UserError for a scene that is no heap, a part count the tote cannot hold, a part too big
        for the hand, a tote the hand cannot reach, a hybrid hand whose fingers cannot keep ``cup_room`` from
        its cup, a tray it cannot use or an out-box on the heap."""
        b = cfg.bin_pick
        if b.scene not in CLUTTER_KINDS:
            raise ConfigError(f"task bin-pick needs scene bin or pile, not {b.scene!r} (--scene, bin_pick.scene)")
        lo, hi = b.clutter.parts
        if not 1 <= lo <= hi:
            raise ConfigError(f"bin_pick.clutter.parts must be 1 <= min <= max, got {list(b.clutter.parts)}")
        types = task_types(cfg)
        too_big = [t.name for t in types if float(np.min(t.extents)) > cfg.grasp.max_width]
        if too_big:
            raise UserError(f"part(s) {too_big} are wider than the hand opens ({cfg.grasp.max_width} m, "
                            "grasp.max_width) every way: choose other scene.block_types or --objects")
        check_clutter(cfg.scene.workcell, b.scene, b.clutter, types, hi)
        if cfg.scene.workcell.hand == "hybrid":  # the fingers' opening round the cup exists
            from posegrasp.grasping.tasks.bin_pick.planner import cup_opening

            cup_opening(cfg.scene.workcell)
        if b.place == "tray":
            from posegrasp.grasping.tasks.bin_pick.tray import check_tray

            check_tray(cfg, tray_of(cfg.scene.workcell, b))
        else:
            check_outbox(cfg.scene.workcell, b)

    def scene(self, cfg: TrialConfig, seed: int, n_blocks: int, graspable: Graspable) -> Workcell:
        return bin_scene(cfg, seed, n_blocks)

    def run(self, ep: Episode) -> None:
        """Attempts until the tote is believed empty (``attempt.empty_tote``)."""
        from posegrasp.grasping.tasks.bin_pick.attempt import empty_tote

        empty_tote(ep)

    def metrics(self, records: list[dict], latency: float = 0.0) -> dict:
        return metrics.bin_metrics(records, latency)

    def print_summary(self, summary: dict, console: Console) -> None:
        """Percent cleared, attempt and grasp success, picks per hour and attempt failures, then how the episodes
        ended (an episode succeeds when it empties the tote)."""
        objects = summary.get("objects", {}).get("name", "blocks")
        console.print(f"[bold]{summary['task']}, {summary['perception']}, {objects}[/]")
        metrics.print_summary(summary["bin_pick"], console)
        print_failures(summary["failures"], "episodes ended by", console)

    def compare(self, a: dict[int, dict], b: dict[int, dict], common: list[int],
                latency: tuple[float, float] = (0.0, 0.0)) -> dict:
        return {"bin_pick": metrics.compare(a, b, common, latency)}

    def judged_by(self, result: dict) -> tuple[float, float]:
        """Reliability (attempt success), else picks per hour where reliability does not differ
        (``metrics.verdict``): the difference B - A and its p-value."""
        diff, p = result["bin_pick"]["judged_by"]
        return diff, p

    def print_comparison(self, result: dict, console: Console) -> None:
        metrics.print_comparison(result["bin_pick"], console)

    def report_page(self, run: TrialRun, samples: int, executor: Executor | None) -> str:
        """Bin picking's statistics and up to ``report.SHOWN`` of the ``samples`` episodes attempt by attempt
        (``report.page``)."""
        from posegrasp.grasping.tasks.bin_pick.report import page

        return page(self, run, samples, executor)
