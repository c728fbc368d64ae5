"""The tote: an open box of five static boxes (floor and four walls) standing on the table in the pick area.

Composed as its own ``dm_control.mjcf`` model and attached to the workcell's MJCF at the pick area centre, so
its geoms are named ``tote/floor``, ``tote/wall_x0`` ... ``tote/wall_y1``. The walls collide with the parts and
the robot, are drawn and seen by the cameras, but are no object of a dataset (no label, no mask).

``check_reach`` proves with the arm's IK (``sim.ik``) that the hand reaches every corner of the floor from
above: top-down, past the walls, the arm, wrist, palm and camera clear of them (the fingers pre-shape to the
part they grasp, so they are checked only on the way in, open, above the walls).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import mujoco
import numpy as np
from dm_control import mjcf

from posegrasp.config import settings, within
from posegrasp.errors import UserError
from posegrasp.geometry import axis_angle_R, make_T
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.shaker import ShakerConfig, add_shaker
from posegrasp.sim.workcell import Workcell

TOTE = "tote"  #: model name of the tote: the prefix of its geoms' names in a workcell
WALLS = ("wall_x0", "wall_x1", "wall_y0", "wall_y1")
SUNK = 0.02  #: depth (m) of the floor's collision box below the table top


@settings
class ToteConfig:
    """An open box centred on the pick area; its inner floor is where bin scenes' parts come to rest."""

    #: Inner floor size (m) along world x and world y, between the walls' inner faces.
    inner_size: tuple[float, float] = field(default=(0.24, 0.28), metadata=within(0.01, 2.0))
    #: Height (m) of the walls' top above the inner floor.
    wall_height: float = field(default=0.06, metadata=within(0.005, 0.5))
    #: Thickness (m) of the walls and of the floor.
    thickness: float = field(default=0.01, metadata=within(0.002, 0.05))
    #: Colour (RGBA in [0, 1]) of the tote as the cameras see it.
    rgba: tuple[float, float, float, float] = (0.22, 0.33, 0.52, 1.0)
    #: Reach check: the pinch point stands this far (m) from both walls of each floor corner ...
    reach_inset: float = field(default=0.035, metadata=within(0.0, 0.5))
    #: ... this high (m) above the inner floor, the gripper pointing straight down ...
    reach_height: float = field(default=0.015, metadata=within(0.0, 0.5))
    #: ... and the approach starts with the pinch point this far (m) above the walls' top.
    reach_approach: float = field(default=0.05, metadata=within(0.0, 0.5))
    #: Least distance (m) from the walls to arm, wrist, palm and camera at the corner grasps, and to the open fingers
    #: above them.
    reach_clearance: float = field(default=0.002, metadata=within(0.0, 0.1))


@dataclass(frozen=True)
class Tote:
    """A tote placed on the table: ``center`` (x, y) of its inner floor in the world frame (m), z up."""

    cfg: ToteConfig
    center: tuple[float, float]

    @staticmethod
    def in_pick_area(workcell: WorkcellConfig, cfg: ToteConfig) -> "Tote":
        """The tote ``cfg`` centred on the workcell's pick area."""
        return Tote(cfg, tuple(float(c) for c in workcell.pick_area.center))

    @property
    def floor_z(self) -> float:
        """Height (m) of the inner floor above the table top."""
        return self.cfg.thickness

    @property
    def top_z(self) -> float:
        """Height (m) of the walls' top above the table top."""
        return self.cfg.thickness + self.cfg.wall_height

    def inner_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World (lo, hi) corners (m) of the inner volume: between the walls, from the floor to the walls' top."""
        h = 0.5 * np.asarray(self.cfg.inner_size, float)
        return np.array([*(self.center - h), self.floor_z]), np.array([*(self.center + h), self.top_z])

    def inner_volume(self) -> float:
        """Inner volume (m^3): floor area times wall height."""
        lo, hi = self.inner_bounds()
        return float(np.prod(hi - lo))

    def contains(self, points: np.ndarray, tol: float = 0.0) -> bool:
        """Whether every world point (N, 3) lies between the walls' inner faces and above the floor, within
        ``tol`` (m); the height is not bounded above (a heap may rise over the walls)."""
        lo, hi = self.inner_bounds()
        p = np.asarray(points, float).reshape(-1, 3)
        return bool(np.all(p[:, :2] >= lo[:2] - tol) and np.all(p[:, :2] <= hi[:2] + tol)
                    and np.all(p[:, 2] >= lo[2] - tol))

    def mjcf_model(self) -> mjcf.RootElement:
        """The tote as its own MJCF model, in a frame at the centre of its bottom on the table: floor and walls."""
        c = self.cfg
        t, hx, hy = c.thickness, 0.5 * c.inner_size[0], 0.5 * c.inner_size[1]
        wh = 0.5 * (t + c.wall_height)  # half height of the walls, which stand on the table around the floor
        root = mjcf.RootElement(model=TOTE)
        kw = dict(type="box", rgba=c.rgba, contype=1, conaffinity=1, group=1, friction=(0.9, 0.01, 0.001))
        # the floor reaches SUNK below the table top (hidden in the table): a part pressed into a thin floor by
        # an impact is pushed back up, never through it
        root.worldbody.add("geom", name="floor", size=(hx, hy, 0.5 * (t + SUNK)), pos=(0, 0, 0.5 * (t - SUNK)), **kw)
        root.worldbody.add("geom", name="wall_x0", size=(0.5 * t, hy + t, wh), pos=(-hx - 0.5 * t, 0, wh), **kw)
        root.worldbody.add("geom", name="wall_x1", size=(0.5 * t, hy + t, wh), pos=(hx + 0.5 * t, 0, wh), **kw)
        root.worldbody.add("geom", name="wall_y0", size=(hx, 0.5 * t, wh), pos=(0, -hy - 0.5 * t, wh), **kw)
        root.worldbody.add("geom", name="wall_y1", size=(hx, 0.5 * t, wh), pos=(0, hy + 0.5 * t, wh), **kw)
        return root

    def add_to(self, root: mjcf.RootElement, shaker: ShakerConfig | None = None) -> None:
        """Attach the tote to a workcell's MJCF ``root`` at ``center`` on the table top: static (no joint), or on
        a ``shaker`` stage (``sim.shaker``)."""
        frame = root.attach(self.mjcf_model())
        frame.pos = (*self.center, 0.0)
        if shaker is not None:
            add_shaker(frame, root, shaker)


def tote_geoms(model: mujoco.MjModel) -> np.ndarray:
    """Ids of a compiled model's tote geoms (floor and walls); empty when it has no tote."""
    return np.array([i for i in range(model.ngeom) if model.geom(i).name.startswith(f"{TOTE}/")], dtype=int)


#: Yaws (deg) of the squeeze axis tried at each corner.
REACH_YAWS = tuple(range(0, 180, 15))


def _corner_poses(tote: Tote, height: float) -> list[list[np.ndarray]]:
    """Per floor corner, top-down gripper poses (pinch site, world) ``reach_inset`` from both walls at ``height``
    above the floor, one per yaw of the squeeze axis in ``REACH_YAWS``."""
    lo, hi = tote.inner_bounds()
    d = tote.cfg.reach_inset
    down = np.diag([1.0, -1.0, -1.0])  # gripper z (approach) along world -z
    out = []
    for x in (lo[0] + d, hi[0] - d):
        for y in (lo[1] + d, hi[1] - d):
            out.append([make_T(axis_angle_R([0.0, 0.0, 1.0], np.deg2rad(yaw)) @ down, (x, y, tote.floor_z + height))
                        for yaw in REACH_YAWS])
    return out


def check_reach(workcell: WorkcellConfig, tote: Tote, pos_tol: float = 0.004, rot_tol: float = 0.02) -> None:
    """Raise a one-line UserError unless the hand reaches every floor corner of ``tote`` from above.

    A corner is reached when, at one of the yaws of ``_corner_poses``, IK puts the pinch point ``reach_height``
    above the floor (and, on the way in, ``reach_approach`` above the walls' top) within ``pos_tol`` m and
    ``rot_tol`` rad, the robot but its fingers (or suction cup) at
    least ``reach_clearance`` from the walls there and the whole
    robot, fingers open, as far from them at the approach pose.
    """
    bad = _unreached_corners(workcell, tote, pos_tol, rot_tol)
    if bad:
        raise UserError(f"the hand cannot reach the tote's floor corner(s) {bad} from above: tote inner size "
                        f"{list(tote.cfg.inner_size)} m, walls {tote.cfg.wall_height} m, centred at "
                        f"{list(tote.center)}; use a smaller or lower tote or move the pick area")


def _gap(m: mujoco.MjModel, d: mujoco.MjData, geoms: np.ndarray, others: np.ndarray) -> float:
    """Least distance (m) between any of ``geoms`` and any of ``others`` (negative: penetration), up to 0.1."""
    return min(mujoco.mj_geomDistance(m, d, int(g), int(o), 0.1, None) for g in geoms for o in others)


@functools.lru_cache(maxsize=8)
def _unreached_corners(workcell: WorkcellConfig, tote: Tote, pos_tol: float, rot_tol: float) -> list[list[float]]:
    """The (x, y) (m) of the floor corners ``check_reach`` finds unreached, cached per workcell and tote."""
    wc = Workcell(workcell, extras=tote.add_to)
    m, d = wc.model, wc.data
    walls = np.array([m.geom(f"{TOTE}/{w}").id for w in WALLS])  # the floor is under the fingertips by design
    robot = np.flatnonzero([m.body(b).name.startswith("jaco_arm/") for b in m.geom_bodyid])
    rigid = np.array([g for g in robot if not any(t in m.geom(g).name for t in ("finger", "suction"))])  # not the tool
    approach = tote.cfg.wall_height + tote.cfg.reach_approach
    bad = []
    for grasps, above in zip(_corner_poses(tote, tote.cfg.reach_height), _corner_poses(tote, approach)):
        for T, T_above in zip(grasps, above):
            q_above, dp, dr = wc.solve_gripper_ik(T_above, wc.look_q)
            if dp > pos_tol or dr > rot_tol:
                continue
            wc.reset(q_above)
            if _gap(m, d, robot, walls) < tote.cfg.reach_clearance:
                continue
            q, dp, dr = wc.solve_gripper_ik(T, q_above)
            if dp > pos_tol or dr > rot_tol:
                continue
            wc.reset(q)
            if _gap(m, d, rigid, walls) >= tote.cfg.reach_clearance:
                break
        else:
            bad.append([round(float(v), 3) for v in grasps[0][:2, 3]])
    return bad
