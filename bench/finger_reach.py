"""How far from a tote wall a part must lie for the hand to squeeze it across the wall, top-down.

The open fingers (``controller.open_finger_points``: their collision meshes, open ``[bin_pick] finger_margin``
wider than the part) come straight down on a part lying on the floor, the pinch point ``pinch`` above the floor.
Printed per hand, part width (along the squeeze axis), pinch height and wall height: how far (mm) the wall-side
finger reaches beyond the part's face below the wall's top, plus ``[bin_pick] wall_clearance``: the least gap between the
part and the wall that such a grasp needs. The fingertip's own reach at the pinch height is the floor of it.
Run: ``.venv/bin/python bench/finger_reach.py``.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from posegrasp.grasping.controller import open_finger_points
from posegrasp.grasping.tasks.bin_pick import BinPickConfig
from posegrasp.sim.config import HANDS, WorkcellConfig

WIDTHS_MM = (25, 30, 40, 50, 64)
PINCH_MM = (12, 20)
WALLS_MM = (60, 45, 30)


def gap_needed(hand: str, width: float, pinch: float, wall: float) -> tuple[float, float]:
    """The gap (m) between the part's face and the wall that a top-down squeeze across the wall needs with ``hand``
    on a part ``width`` (m) across, pinched ``pinch`` (m) above the floor, below walls ``wall`` (m) high; and the
    fingertip's part of it (the reach at the pinch height)."""
    margin, clearance = BinPickConfig().finger_margin, BinPickConfig().wall_clearance
    p = open_finger_points(WorkcellConfig(hand=hand), round(1000 * (width + margin)))
    above_floor = pinch - p[:, 2]  # the gripper z axis points down, from the palm to the fingertips
    below_top = p[(above_floor < wall) & (p[:, 0] > 0)]
    at_pinch = p[(abs(p[:, 2]) < 0.005) & (p[:, 0] > 0)]
    return below_top[:, 0].max() - width / 2 + clearance, at_pinch[:, 0].max() - width / 2 + clearance


def main() -> None:
    print("hand      width  pinch   gap needed (mm) below walls of " + "  ".join(f"{w} mm" for w in WALLS_MM)
          + "   fingertip")
    for hand in (h for h in HANDS if h != "suction"):  # the cup has no fingers
        for w in WIDTHS_MM:
            for h in PINCH_MM:
                gaps = [gap_needed(hand, w / 1000, h / 1000, wall / 1000) for wall in WALLS_MM]
                print(f"{hand:9} {w:4d}   {h:4d}   " + "".join(f"{1000 * g:11.1f}" for g, _ in gaps)
                      + f"{1000 * gaps[0][1]:14.1f}")


if __name__ == "__main__":
    main()
