"""The trial tasks, by name (``--task``): pick-and-place, kitting into a fixed orientation, stacking, bin picking.

Each task is a module here holding its settings, scene, looks, acceptance of the campaign's settings, goal and
verdict (``pick_place.py``, ``kitting.py``, ``stack.py``, ``bin_pick.py``); ``base.py`` holds the ``Task`` protocol and says how to
write one.
"""

from __future__ import annotations

from posegrasp.errors import UserError
from posegrasp.grasping.tasks.base import Task
from posegrasp.grasping.tasks.bin_pick import BinPickTask
from posegrasp.grasping.tasks.kitting import Kitting
from posegrasp.grasping.tasks.pick_place import PickPlace
from posegrasp.grasping.tasks.stack import Stack

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
