"""The trial tasks, by name (``--task``): pick-and-place, kitting into a fixed orientation, stacking, bin picking.

Each task is a module here holding its settings, scene, looks, acceptance of the campaign's settings, goal and
verdict (``pick_place.py``, ``kitting.py``, ``stack.py``, the package ``bin_pick/``); ``base.py`` holds the ``Task`` base
class and says how to write one. This registry is loaded by the drivers (``trials``, ``captures``, ``compare``, the
report, the command line), never by what the tasks use, so a task may use every other module of ``grasping``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

from posegrasp.errors import ConfigError, UserError
from posegrasp.grasping.tasks.base import Task
from posegrasp.grasping.tasks.bin_pick import BinPickTask
from posegrasp.grasping.tasks.kitting import Kitting
from posegrasp.grasping.tasks.pick_place import PickPlace
from posegrasp.grasping.tasks.stack import Stack
from posegrasp.sim.config import HANDS

if TYPE_CHECKING:
    from posegrasp.grasping.config import TrialConfig

#: The tasks by ``--task`` name, the default first.
REGISTRY: dict[str, Task] = {t.name: t for t in (PickPlace(), Kitting(), Stack(), BinPickTask())}
#: The ``--task`` names.
TASKS = tuple(REGISTRY)


def get_task(name: str) -> Task:
    """The task called ``name``; a UserError naming the choices if there is none."""
    try:
        return REGISTRY[name]
    except KeyError:
        raise UserError(f"unknown task {name!r}; choose one of: {', '.join(TASKS)}") from None


def check_task(cfg: TrialConfig) -> None:
    """ConfigError unless ``cfg.task`` and ``cfg.firm_hold_tasks`` name tasks and the task accepts the campaign's
    settings (``Task.check``: the scene's block types can serve it, ...)."""
    from posegrasp.grasping.config import firm_hold_tasks

    task = get_task(cfg.task)
    if cfg.scene.workcell.hand not in HANDS:
        raise ConfigError(f"scene.workcell.hand {cfg.scene.workcell.hand!r} is not a hand; choose one of: "
                          f"{', '.join(HANDS)}")
    if cfg.scene.workcell.hand == "suction" and not task.suction:
        raise ConfigError(f"the suction tool (--hand suction) picks only in bin picking, not in the {task.name} task: "
                          "use --task bin-pick or another --hand")
    unknown = [t for t in firm_hold_tasks(cfg) if t not in TASKS]
    if unknown:
        raise ConfigError(f"firm_hold_tasks names unknown task(s) {unknown}; choose among: {', '.join(TASKS)}")
    task.check(cfg)


def with_set(cfg: TrialConfig, objects: str | Path | None = None) -> TrialConfig:
    """``cfg`` on the object set ``objects`` (None: the one ``cfg`` names; ``""``: the shipped blocks), its folder
    made absolute and checked (``sim.config.with_objects``), and its firm-hold tasks settled (``firm_hold_tasks``,
    so the campaign records them)."""
    from posegrasp.grasping.config import firm_hold_tasks
    from posegrasp.sim.config import with_objects

    cfg = dataclasses.replace(cfg, scene=dataclasses.replace(cfg.scene, workcell=with_objects(cfg.scene.workcell,
                                                                                               objects)))
    return dataclasses.replace(cfg, firm_hold_tasks=firm_hold_tasks(cfg))
