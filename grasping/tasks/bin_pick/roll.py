"""Rolls off a wall: the hybrid hand's nudge for a round part lying on its side by a tote wall.

A cylinder lying on its side within a finger's reach of a wall (``squeeze.NEAR_WALL``) shows the cup no face it
seals on (its side curves 3.8 mm under a 20 mm rim) and the fingers no room on the wall's side; in a corner its end
disc is on the other wall, so no squeeze along the wall either: nothing graspable. It rolls, though. The closed
fingertips come down on its top line ``BEHIND`` (m) from the top on the wall's side, press ``PRESS`` (m) into it and
move across its axis, away from the wall: the part rolls under them as a rolling pin under a palm, its axis going
half as far as the hand where nothing slips (``ROLL_RATIO``: 0.44 measured on the shipped cylinder), so the top line
falls back along the pad,

    stroke length = (pad + behind) / (1 - ROLL_RATIO)    (the top line at the pad's back edge)

then up, back to the top line and again, until the part lies ``ROLL_TO`` (m) from every wall it rolls away from,
where the fingers reach round it. The roll is planned from the estimate alone: a part with a continuous symmetry
whose axis lies within ``LEVEL_DEG`` of horizontal, resting on the floor; the closed fingers' meshes and the camera
keep ``wall_clearance`` from the walls, the fingers' boxes (``planner.finger_boxes``) and the camera the loosest
``part_clearance`` from the other parts, at the first and the last stroke; the part's rolled pose keeps
``PART_ROOM`` from the other parts. A roll picks nothing: its attempt fails ("rolled off a wall"), and the next look
picks the part where it came to rest.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from posegrasp.catalog import PartType
from posegrasp.geometry import axis_angle_R, make_T, transform_points
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.grasps import Grasp
from posegrasp.grasping.hand import camera_box
from posegrasp.grasping.record import Failure
from posegrasp.grasping.tasks.base import EpisodeFailed
from posegrasp.grasping.tasks.bin_pick.planner import (HeapView, _clear_of, _fingers_inside, _first_reachable, _tried,
                                                        finger_boxes, pregrasp_height)
from posegrasp.grasping.tasks.bin_pick.scene import Area
from posegrasp.grasping.tasks.bin_pick.squeeze import NEAR_WALL
from posegrasp.sim.hybrid import extend
from posegrasp.sim.workcell import Workcell

#: The part's axis moves this share of the hand's move (the shipped cylinder: 0.44).
ROLL_RATIO = 0.4
#: The fingertips press this far (m) into the part's estimated top ...
PRESS = 0.002
#: ... this far (m) from its top line on the wall's side (the top line falls back along the pad as they move), the
#: first stroke at the first of ``BEHINDS`` (m) that keeps the hand off the wall.
BEHIND = 0.005
BEHINDS = (0.005, 0.002, -0.001, -0.004)
#: The hand rises this far (m) between strokes, and moves at this speed (m/s) on the part (elsewhere at the arm's).
LIFT, ROLL_SPEED = 0.015, 0.05
#: A part is rolled until it lies this far (m) from the walls it rolls away from (the fingers' reach: 29-35 mm) ...
ROLL_TO = 0.04
#: ... in at most this many strokes; a wall counts when the roll's direction lies within 45 deg of its normal.
MAX_STROKES, ACROSS = 6, math.cos(math.radians(45.0))
#: A round part rolls when its axis lies within this angle (deg) of horizontal, on the floor (within ``ON_FLOOR``, m).
LEVEL_DEG, ON_FLOOR = 10.0, 0.003
#: The hand leans by these angles (deg, either way) along the part's axis, its top away from a wall across its end,
#: the closed fingertips on the part's top line: the least that clears the walls.
TILTS_DEG = (0.0, 15.0, -15.0, 30.0, -30.0)
#: The rolled part keeps this far (m) from the other parts' estimated surfaces and the depth image's points.
PART_ROOM = 0.003


@dataclass(frozen=True)
class Roll(Grasp):
    """A roll off a wall (``wall_rolls``): the closed fingertips' first pose on the part (world gripper: z down, x
    along the part's axis, ``behind`` (m) from its top line on the wall's side), the horizontal ``direction``
    (world) it rolls in and its strokes' ``lengths`` (m). ``width`` is 0: the fingers stay closed."""

    direction: tuple[float, float, float] = (0.0, 0.0, 0.0)
    behind: float = BEHIND
    lengths: tuple[float, ...] = ()

    @property
    def shift(self) -> np.ndarray:
        """(3,) how far (m, world) the part's axis moves in the whole roll: ``ROLL_RATIO`` of the strokes."""
        return ROLL_RATIO * sum(self.lengths) * np.asarray(self.direction)

    def stroke(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Stroke ``i``'s start and end poses (world gripper): each after the first starts ``BEHIND`` from where the
        part's top line will be (``ROLL_RATIO`` of the strokes before)."""
        d = np.asarray(self.direction)
        start = self.T_world_gripper.copy()
        if i:
            start[:3, 3] += (self.behind - BEHIND + ROLL_RATIO * sum(self.lengths[:i])) * d
        end = start.copy()
        end[:3, 3] += self.lengths[i] * d
        return start, end


def stroke_length(behind: float, pad: float) -> float:
    """How far (m) the hand may move in a stroke that starts ``behind`` (m) from the part's top line, its pad
    reaching ``pad`` (m) back from the fingertips' centre: the top line falls back along the pad by
    ``1 - ROLL_RATIO`` of the hand's move, and leaves it at its back edge."""
    return (pad + behind) / (1.0 - ROLL_RATIO)


def fingertips(wc_cfg) -> tuple[float, float]:
    """The closed fingertips (``planner.finger_boxes``' lowest slice, the two fingers side by side): how far (m) they
    reach past the pinch point along the gripper's z axis, and their pad's least half-width (m) along its x or y axis
    (the pad's reach back from its centre whichever way the hand is turned)."""
    lo, hi = max(finger_boxes(wc_cfg, 0.0), key=lambda box: box[1][2])
    return float(hi[2]), float(min(-lo[1], hi[1], max(abs(lo[0]), abs(hi[0]))))


def wall_rolls(part: PartType, T_world_obj: np.ndarray, area: Area, tip: float, pad: float) -> list[Roll]:
    """Rolls of ``part`` at its estimated ``T_world_obj`` (levelled) away from the tote walls nearer than
    ``NEAR_WALL`` (m), if it is round (a continuous symmetry), lies on its side on the floor and near a wall, in the
    strokes (at most ``MAX_STROKES``) that bring it ``ROLL_TO`` from those walls, per first stroke's ``BEHINDS``
    (``_placed``; ``fingertips``: ``tip`` and ``pad``, m); ``clearance`` is left at 0. None when it is not such a
    part."""
    if not part.symmetries_continuous:
        return []
    a_obj, c_obj = (np.asarray(x, float) for x in part.symmetries_continuous[0])
    axis = T_world_obj[:3, :3] @ a_obj
    v = transform_points(T_world_obj, part.vertices)
    if abs(axis[2]) > math.sin(math.radians(LEVEL_DEG)) or v[:, 2].min() - area.floor > ON_FLOOR:
        return []
    axis = np.array([axis[0], axis[1], 0.0]) / np.linalg.norm(axis[:2])
    lo, hi = area.tote.inner_bounds()
    gaps = np.array([v[:, 0].min() - lo[0], hi[0] - v[:, 0].max(), v[:, 1].min() - lo[1], hi[1] - v[:, 1].max()])
    inward = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    near = gaps < NEAR_WALL
    d = np.cross(axis, (0.0, 0.0, 1.0))
    d *= 1.0 if (inward[near] @ d).sum() >= 0.0 else -1.0
    away = near & (inward @ d > ACROSS)  # the walls it rolls away from
    if not away.any():
        return []
    travel = float(max((ROLL_TO - gaps[away]) / (inward[away] @ d)))
    rolls = []
    for behind in BEHINDS:
        lengths = [stroke_length(behind, pad)]
        while ROLL_RATIO * sum(lengths) < travel and len(lengths) < MAX_STROKES:
            lengths.append(stroke_length(BEHIND, pad))
        end = v[:, :2] + ROLL_RATIO * sum(lengths) * d[:2]  # no nearer a wall than it lies, nor than PART_ROOM
        end_gaps = np.concatenate([end.min(0) - lo[:2], hi[:2] - end.max(0)])[[0, 2, 1, 3]]
        if ROLL_RATIO * sum(lengths) >= travel and np.all(end_gaps >= np.minimum(gaps, PART_ROOM) - 1e-6):
            rolls += _placed(v, T_world_obj[:3, 3], axis, d, tip, behind, tuple(lengths))
    return rolls


def _placed(v: np.ndarray, origin: np.ndarray, axis: np.ndarray, d: np.ndarray, tip: float, behind: float,
            lengths: tuple[float, ...]) -> list[Roll]:
    """The rolls of a part (its vertices ``v``, world) along ``d``: the fingertips (``tip`` m past the pinch point)
    ``behind`` (m) from its top line near either end and at its middle, the hand's x axis either way along the
    part's ``axis``, then along the wall nearest that direction (the closed fingers spread along x as they rise; across
    the part, the gap between the two fingertips would meet its top line), leaning along x by each of
    ``TILTS_DEG``."""
    t = (v - origin) @ axis
    centre = origin + 0.5 * (t.min() + t.max()) * axis
    half = 0.5 * float(np.ptp(t)) - 0.008
    rolls = []
    wall = [w for w in (*np.eye(3)[:2], *-np.eye(3)[:2]) if w @ axis > ACROSS]  # the wall direction nearest the axis
    for x0, deg, s, sign in itertools.product([axis, *wall], TILTS_DEG, sorted({0.0, half, -half}, key=abs), (1, -1)):
        x = sign * x0
        R = np.stack([x, np.cross((0.0, 0.0, -1.0), x), (0.0, 0.0, -1.0)], 1)
        R = axis_angle_R(R[:, 1], math.radians(deg)) @ R  # the hand's top leaning along the part's axis
        contact = centre + s * axis - behind * d
        contact[2] = v[:, 2].max() - PRESS
        rolls.append(Roll(make_T(R, contact - tip * R[:, 2]), 0.0, clearance=0.0, tilt_deg=deg, support=0.0,
                          score=0.0, direction=tuple(float(c) for c in d), behind=behind, lengths=lengths))
    return rolls


def choose_roll(wc: Workcell, cfg: TrialConfig, view: HeapView, failed: list[np.ndarray]
                ) -> tuple[int, Roll, np.ndarray]:
    """The estimate of ``view`` to roll off a wall (index), its ``wall_rolls`` roll and its levelled
    ``T_world_obj``: of the rolls whose closed fingers and camera clear the walls and the other parts at the first
    and the last stroke, and whose rolled part clears the other parts, the highest part's with the most room from the
    walls, the best the arm reaches, none that ``failed`` before; ``EpisodeFailed`` ("nothing graspable",
    "unreachable") as ``planner.choose_part``."""
    b, area = cfg.bin_pick, view.area
    if not area.walls:
        raise EpisodeFailed(Failure.NOTHING_GRASPABLE)
    cam, fingers = camera_box(wc.cfg.hand_camera.mount_pos), list(finger_boxes(wc.cfg, 0.0))
    tip, pad = fingertips(wc.cfg)

    def clear(g: Grasp, others: np.ndarray, wall: np.ndarray) -> bool:
        return (_clear_of(g, wall, [cam], b.wall_clearance)
                and _fingers_inside(g, wc.cfg, 0.0, area.tote, b.wall_clearance)
                and _clear_of(g, others, [*fingers, cam], b.part_clearance[-1]))

    def ranked(j: int) -> list[tuple[float, Roll]]:
        own, others, wall = view.around(j)
        out = []
        for g in wall_rolls(view.part(j), view.poses[j], area, tip, pad):
            ends = [dataclasses.replace(g, T_world_gripper=T) for T in (g.stroke(0)[0], g.stroke(len(g.lengths) - 1)[1])]
            if _tried(g, failed, b) or not all(clear(e, others, wall) for e in ends):
                continue
            moved = own.data + g.shift
            if len(others) and cKDTree(moved).query(others, distance_upper_bound=PART_ROOM)[0].min() < PART_ROOM:
                continue
            out.append((b.height_weight * (view.tops[j] - area.floor), g))
        return out

    return _first_reachable(wc, cfg, view, [ranked])


def roll_off(ep, roll: Roll, area: Area, watch) -> None:
    """Roll a part off the wall with the closed fingers (``Roll``: its strokes, each from above the part's top line,
    down, across, up), the contact monitor ``watch`` (``pick._Contacts``) making a protective stop at a wall. Always
    ends the attempt: ``EpisodeFailed`` ("rolled off a wall"), or the monitor's reason."""
    ctl, cfg = ep.ctl, ep.cfg
    ctl.hold(extend(ep.wc, False))
    ctl.preshape(0.0)
    ctl.monitor = watch
    try:
        for i in range(len(roll.lengths)):
            start, end = roll.stroke(i)
            above = start.copy()
            above[2, 3] += LIFT if i else pregrasp_height(cfg, area, start)
            if not ctl.move(above, reposture=not i):
                raise EpisodeFailed(Failure.TIMEOUT)
            ctl.move(start, speed=cfg.grasp.approach_speed)  # pressed into the part: short of it
            ctl.move(end, speed=ROLL_SPEED)
            end[2, 3] += LIFT
            ctl.move(end)
    finally:
        ctl.monitor = None
    raise EpisodeFailed(Failure.ROLLED)
