"""Squeezes along a wall: the fingers' last resort for a part turned on the floor near a tote wall.

A part lying nearer a wall than a finger reaches down (``bench/finger_reach.py``: 29-35 mm) is pinched along the
wall by the planner (``planner.choose_part``) only where two of its faces face along the wall. A part turned on the
floor, its faces at 20-45 deg to the wall, shows no such pair, and a 2x2 brick on its side shows the cup no face it
seals on (its sides are 19 mm high, the cup 20 mm across): nothing graspable. Fingers squeezing such a part along the
wall turn it square to their pads as they close where it is free to turn (a squeeze orients a polygon: Goldberg,
"Orienting polygonal parts without sensors", Algorithmica 1993) and hold it by two edges where a wall keeps it from
turning, so the pinch needs no face pair: its axis ``a`` runs along the wall, its centre is the middle of the part's
estimated extent along ``a`` and across it (moved off that middle, away from the wall, the pads meet the part off
centre and a turned part may turn out of them in the lift: the centre moves ``OFF_WALL`` away from the wall only where
the hand would not clear it, the least that does), at half the part's height (at least ``PINCH_BELOW_TOP`` below its top
and ``grasp.min_pinch_height`` above the floor), and the fingers open ``finger_margin`` wider than the extent along
``a``.

    a = +-e_y for the x walls, +-e_x for the y walls (both signs: the hand camera on either side)

The open hand and its camera keep ``wall_clearance`` from the walls and the loosest ``part_clearance`` from the other
parts, as any grasp, and the open fingers off the part's own surface; of the squeezes the arm reaches
(``planner._first_reachable``), the one on the highest part with the most room between the hand and the walls (the
squeezed part pushes the hand back toward the wall).
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import numpy as np

from posegrasp.catalog import PartType
from posegrasp.geometry import transform_points
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.grasps import Grasp
from posegrasp.grasping.hand import camera_box, hand_of
from posegrasp.grasping.record import Failure
from posegrasp.grasping.tasks.base import EpisodeFailed
from posegrasp.grasping.tasks.bin_pick.planner import (HeapView, _clear_of, _fingers_inside, _first_reachable,
                                                        _tried, open_fingers)
from posegrasp.grasping.tasks.bin_pick.scene import Area
from posegrasp.sim.workcell import Workcell


@dataclass(frozen=True)
class Squeeze(Grasp):
    """A squeeze along a wall (``wall_squeezes``): a ``Grasp`` whose descent, near the tote's near wall where the
    IK's posture term holds the hand up to 9 mm off, gets the controller's ``reposture``; its centre lies
    ``off_wall`` (m) from the middle of the part, away from the wall."""

    off_wall: float = 0.0


#: A wall nearer the part than this (m) is one to squeeze along: more than a finger's reach down beside a part.
NEAR_WALL = 0.035
#: A squeeze's centre moves this far (m) off the part's middle, away from the wall, the least whose hand clears it.
OFF_WALL = (0.0, 0.002, 0.004, 0.006, 0.008)
#: The squeeze's pinch point lies at least this high (m): this far below the part's top (the fingertips, 8 mm below
#: the pinch point, clear of the floor where the arm ends a descent near the tote's near wall a few mm low).
PINCH_BELOW_TOP = 0.012


def wall_squeezes(part: PartType, T_world_obj: np.ndarray, area: Area, min_pinch_height: float,
                  max_width: float) -> list[Squeeze]:
    """Squeezes of ``part`` at its estimated ``T_world_obj`` along each tote wall nearer than ``NEAR_WALL`` (m),
    nearest wall first, both signs of the pinch axis, each moved off the wall by every ``OFF_WALL`` (the module's
    docstring); none wider than ``max_width`` (m). Poses are the gripper's (world, z straight down, x the pinch axis);
    ``clearance`` is left for ``wall_room``."""
    v = transform_points(T_world_obj, part.vertices)
    lo, hi = area.tote.inner_bounds()
    gaps = np.array([v[:, 0].min() - lo[0], hi[0] - v[:, 0].max(), v[:, 1].min() - lo[1], hi[1] - v[:, 1].max()])
    centre = 0.5 * (v.min(0) + v.max(0))
    centre[2] = max(centre[2], v[:, 2].max() - PINCH_BELOW_TOP, area.floor + min_pinch_height)
    grasps = []
    for w in np.argsort(gaps, kind="stable"):
        if gaps[w] > NEAR_WALL:
            break
        along = np.eye(3)[1 if w < 2 else 0]
        width = float(np.ptp(v @ along))
        if width > max_width:
            continue
        inward = np.eye(3)[w // 2] * (1.0 if w % 2 == 0 else -1.0)  # the wall's normal into the tote
        for a, off in itertools.product((along, -along), OFF_WALL):
            T = np.eye(4)
            T[:3, 0], T[:3, 1], T[:3, 2] = a, np.cross((0.0, 0.0, -1.0), a), (0.0, 0.0, -1.0)
            T[:3, 3] = centre + off * inward
            grasps.append(Squeeze(T, width, clearance=0.0, tilt_deg=0.0, support=0.0, score=0.0, off_wall=off))
    return grasps


def wall_room(grasp: Grasp, wc_cfg, margin: float, area: Area, camera: tuple) -> float:
    """The least distance (m) between the tote's inner walls and the open fingers (``planner.open_fingers``; their
    mesh points below the walls' top) or the ``camera`` box's corners."""
    lo, hi = area.tote.inner_bounds()
    pts = open_fingers(grasp, wc_cfg, margin)
    corners = transform_points(grasp.T_world_gripper, np.array(list(itertools.product(*zip(*camera)))))
    low = np.concatenate([pts[pts[:, 2] < hi[2], :2], corners[corners[:, 2] < hi[2], :2]])
    return float(np.minimum(low - lo[:2], hi[:2] - low).min(initial=1.0))


def choose_squeeze(wc: Workcell, cfg: TrialConfig, view: HeapView, failed: list[np.ndarray]
                   ) -> tuple[int, Grasp, np.ndarray]:
    """The estimate of ``view`` to squeeze along a wall (index), its ``wall_squeezes`` grasp and its levelled ``T_world_obj``:
    the highest parts' squeezes whose open hand and camera clear the walls and the other parts, the best the arm
    reaches, none that ``failed`` before; ``EpisodeFailed`` ("nothing graspable", "unreachable") as
    ``planner.choose_part``."""
    b, g_cfg, area = cfg.bin_pick, cfg.grasp, view.area
    if not area.walls:
        raise EpisodeFailed(Failure.NOTHING_GRASPABLE)
    cam, hand = camera_box(wc.cfg.hand_camera.mount_pos), hand_of(wc.cfg)

    def ranked(j: int) -> list[tuple[float, Grasp]]:
        own, others, wall = view.around(j)
        grasps, axes = [], set()
        for g in wall_squeezes(view.part(j), view.poses[j], area, g_cfg.min_pinch_height, g_cfg.max_width):
            axis = tuple(np.round(g.T_world_gripper[:3, 0], 6))  # per pinch axis, the least move off the wall
            if (axis not in axes and not _tried(g, failed, b) and _clear_of(g, wall, [cam], b.wall_clearance)
                    and _fingers_inside(g, wc.cfg, b.finger_margin, area.tote, b.wall_clearance)
                    and _clear_of(g, own.data, hand.boxes((g.width + b.finger_margin) / 2)[:-1], 0.0)
                    and _clear_of(g, others, [*hand.boxes((g.width + b.finger_margin) / 2), cam],
                                  b.part_clearance[-1])):
                axes.add(axis)
                grasps.append(dataclasses.replace(g, clearance=wall_room(g, wc.cfg, b.finger_margin, area, cam)))
        return [(b.height_weight * (view.tops[j] - area.floor + g.clearance), g) for g in grasps]

    return _first_reachable(wc, cfg, view, [ranked])
