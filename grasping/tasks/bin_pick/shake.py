"""Shaking the tote: parts that lie against the walls, where neither the fingers nor the cup reach them (a part
0-18 mm from a wall needs 29-35 mm for the fingers; a brick lying studs up gives the cup no seal), are shaken off
the walls by the tote's stage (``sim.shaker``): after a look that finds nothing graspable, the robot waiting, and
(``shake_away``) while the arm carries a part off and comes back, as a flexible feeder shakes while the robot is
away, so that the next look finds those parts off the walls.

The direction comes from the estimates only: the sum of the outward normals of the walls that each estimate's
centre lies within ``shake_margin`` of. The tote jerks toward those walls, so the parts slide away from them;
a part in a corner leaves both walls.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from posegrasp.grasping.tasks.bin_pick.scene import Area

if TYPE_CHECKING:
    from posegrasp.grasping.episode import Episode
    from posegrasp.sim.shaker import Shaker


def shake_direction(area: Area, poses: list[np.ndarray], margin: float) -> np.ndarray | None:
    """Unit vector (world xy) the tote should jerk along, from the estimated poses ``poses`` (T_world_obj, m): the
    normalised sum, over poses, of the outward normals of the walls whose inner face the pose's origin lies within
    ``margin`` (m) of; None where no estimate lies that near a wall (or the walls' pulls cancel)."""
    lo, hi = area.tote.inner_bounds()
    u = np.zeros(2)
    for T in poses:
        xy = T[:2, 3]
        u += (hi[:2] - xy < margin).astype(float) - (xy - lo[:2] < margin).astype(float)
    n = float(np.linalg.norm(u))
    return u / n if n > 0.0 else None


class Shake:
    """A shake of the tote's stage along the unit vector ``u`` (world xy), under way from now on while the robot
    does what it does (``Workcell.background``: the set point renewed before each physics step, so that the tote
    never sleeps while it shakes); ``finish`` waits out the rest of it."""

    def __init__(self, ep: Episode, shaker: Shaker, u: np.ndarray):
        self.ep, self.shaker, self.u = ep, shaker, u
        self.t0 = ep.wc.data.time
        ep.wc.background = self

    def __call__(self) -> None:
        self.shaker.set_point(self.shaker.offset(self.u, self.ep.wc.data.time - self.t0))

    def finish(self) -> None:
        """Hold the arm where it is until the shake is over (the parts at rest), and end it."""
        ctl = self.ep.ctl
        ctl.hold(max(0.0, self.t0 + self.shaker.duration - self.ep.wc.data.time))
        self.ep.wc.background = None
        self.shaker.set_point(np.zeros(2))
        self.ep.log.stop("shake", ctl, add=True)
