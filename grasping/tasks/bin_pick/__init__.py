"""The bin-picking task: one episode empties one tote (``--scene bin``) or one heap on the table (``--scene pile``)
into an out-box beside it, attempt after attempt.

Each attempt looks down at the tote from above (capture ``im_id`` = the attempt's index), perceives, chooses the
next part among the estimates, picks it with a grasp clear of the tote's walls, the neighbours' estimated surfaces
and the depth image, lifts it clear of the walls and drops it into the out-box (``attempt``). The
episode ends when the robot sees nothing left to pick, when it sees again what it saw when it found no grasp on any
part (that look is no attempt), after ``max_failures`` failed attempts in a row, or after
``attempts_per_part`` attempts per part present. Every attempt is recorded (``record.Attempt``); the episode's
record (``record.BinPickRecord``) says how many parts went into the out-box.

Its scene: ``sim.clutter``'s heap of parts (``ClutterConfig.parts``, drawn per episode) settled in the tote or on
the table, and the out-box (a tote of its own, ``outbox``) beside it (``outbox_offset``). Its summary
(``metrics``): percent cleared per episode (mean, t 95 % interval), attempt success (Wilson 95 %), grasp success
(the attempts that went for a part: VGN's grasp success rate, where a look that finds no grasp is no grasp), picks
per simulated hour, attempt failures by reason, success by part type and by the target's visible fraction.

The package: ``config.py`` its settings, ``scene.py`` the heap, the tote and the out-box, ``planner.py`` the part
choice and the grasp's fit between walls and neighbours, ``attempt.py`` the attempt loop and its verdicts,
``record.py`` its records, ``metrics.py`` its summary and comparison, ``report.py`` its report page, ``task.py``
the ``Task``.
"""

from posegrasp.grasping.tasks.bin_pick.config import BIN_PICK, BinPickConfig
from posegrasp.grasping.tasks.bin_pick.task import BinPickTask

__all__ = ["BIN_PICK", "BinPickConfig", "BinPickTask"]
