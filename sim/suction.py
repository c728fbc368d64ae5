"""The vacuum tool of ``WorkcellConfig.hand = "suction"``: a bellows suction cup on the Jaco2's wrist (its MJCF and
its geometry for a planner), its seal model and its hold model (``SuctionConfig`` holds the settings). The hybrid
hand (``sim.hybrid``) carries the same cup between the 2-finger hand's fingers; seal, hold and ``cup_pose`` serve
both.

Frames: the cup frame is the gripper frame (``workcell.GRIPPER_SITE``: z along the approach direction, into the
part) carried along by the bellows, its origin at the rim's centre; with the bellows at rest (uncompressed) the two
coincide. Lengths m, forces N, torques N m, pressures Pa (kPa in ``SuctionConfig``), times s.

Seal (Dex-Net 3.0's rim test): the rim, sampled at ``RIM_POINTS`` points, seals where the part's true surface under
each point, along the approach axis, lies within ``seal_tolerance`` of the rim: a flat enough patch, not across an
edge, over studs or a hole, nor on a tight curve. ``seal_on_mesh`` tests any mesh at any pose (a planner's
estimate); ``seal_check`` a workcell's part at its true pose.

Hold: at a seal a weld equality constraint (one per part, ``weld_name``) switches on and the part follows the cup;
each control period ``Vacuum.check`` compares the cup's load on the part (the weld's force and the cup's contacts
on it: weight, inertia, a pick off the centre of mass, a drag) with what the vacuum resists (``load_ratio``) and
releases the part when the load is more.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np
from dm_control import mjcf

from posegrasp.errors import ConfigError
from posegrasp.geometry import R_to_quat, invert, make_T
from posegrasp.sim.config import AMBIENT_KPA, SuctionConfig

if TYPE_CHECKING:
    from posegrasp.sim.workcell import Workcell

Box = tuple[tuple[float, float, float], tuple[float, float, float]]

#: The hands with the cup: the vacuum tool and the 2-finger hand with the cup between its fingers (``sim.hybrid``).
CUP_HANDS = ("suction", "hybrid")
#: Points sampled on the rim for the seal test.
RIM_POINTS = 32
#: Names in the hand's model (``jaco_arm/jaco_hand/...`` in a workcell): the cup's body on its slide joint, the
#: rim centre's site, the bellows' and the stem's geoms.
CUP_BODY, SLIDE_JOINT, RIM_SITE = "suction_cup", "suction_slide", "suction_rim"
BELLOWS_GEOM, STEM_GEOM = "suction_bellows", "suction_stem"
#: The palm's face (m along the gripper z axis; the gripper origin lies 72 mm past it) and the palm as a box
#: (min corner, max corner; m, gripper frame), up out of reach like ``grasping.hand.PALM``.
PALM_Z = -0.072
PALM_BOX: Box = ((-0.06, -0.065, -1.0), (0.06, 0.035, -0.07))
#: Radius (m) of the rigid stem from the palm to the bellows.
STEM_RADIUS = 0.008
#: The bellows' spring (N/m) and damper (N s/m) along the approach axis: 3 N at the default 10 mm stroke, critically
#: damped on the cup's mass (kg).
BELLOWS_STIFFNESS, BELLOWS_DAMPING, CUP_MASS, STEM_MASS = 300.0, 5.0, 0.015, 0.03
#: Volume (m^3) of the hose and valve the pump evacuates with the cup (40 cm of 4 mm hose).
HOSE_VOLUME = 5e-6
#: The welds' constraint softness (MuJoCo ``solref``, ``solimp``).
WELD_SOLREF, WELD_SOLIMP = (0.02, 1.0), (0.9, 0.95, 0.001, 0.5, 2.0)
GRAVITY = np.array([0.0, 0.0, -9.81])
_RUBBER, _STEEL = (0.12, 0.13, 0.16, 1.0), (0.62, 0.63, 0.66, 1.0)
_HAND_CONTACT = dict(contype=3, conaffinity=2)  # as the Jaco hand's geoms: touch the parts, table and tote


def weld_name(k: int) -> str:
    """Name of the weld equality constraint holding part ``k`` (1-based) to the cup."""
    return f"suction_{k}"


# -- geometry -----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ToolCylinder:
    """A piece of the tool: a cylinder on the gripper z axis of ``radius`` (m) from ``z0`` to ``z1`` (m, gripper
    frame, z0 < z1; the rim at z = 0)."""

    radius: float
    z0: float
    z1: float

    def box(self) -> Box:
        """Its bounding box (min corner, max corner; m, gripper frame)."""
        r = self.radius
        return (-r, -r, self.z0), (r, r, self.z1)


def rim_radius(cfg: SuctionConfig) -> float:
    """Radius (m) of the cup's rim."""
    return cfg.diameter / 2.0


def cup_height(cfg: SuctionConfig) -> float:
    """Height (m) of the bellows at rest: twice the stroke (its folds close to half)."""
    return 2.0 * cfg.stroke


def tool_cylinders(cfg: SuctionConfig) -> tuple[ToolCylinder, ToolCylinder]:
    """The stem (from the palm to the bellows) and the cup at rest (rim at z = 0), gripper frame: the tool's
    collision volume below the palm. Compressed by ``s`` m, the cup's pieces move ``s`` up (-z)."""
    h = cup_height(cfg)
    return ToolCylinder(STEM_RADIUS, PALM_Z - 0.003, -h), ToolCylinder(rim_radius(cfg), -h, 0.0)


def tool_boxes(cfg: SuctionConfig) -> list[Box]:
    """The tool for a clearance check, as ``grasping.hand.Hand.boxes`` gives a hand: the bounding boxes of the
    stem and the cup at rest, and the palm (the hand camera: ``grasping.hand.camera_box``)."""
    return [c.box() for c in tool_cylinders(cfg)] + [PALM_BOX]


def rim_points(cfg: SuctionConfig, n: int = RIM_POINTS) -> np.ndarray:
    """(n, 3) points (m) on the rim, in the cup frame (z = 0)."""
    a = 2.0 * np.pi * np.arange(n) / n
    return rim_radius(cfg) * np.column_stack([np.cos(a), np.sin(a), np.zeros(n)])


# -- the model ------------------------------------------------------------------------------------------------------
def add_tool(hand: mjcf.RootElement, T_hand_gripper: np.ndarray, cfg: SuctionConfig) -> mjcf.Element:
    """Make dm-control's 3-finger hand the vacuum tool: the fingers go (bodies, actuators and contact exclusions);
    a steel stem comes out of the palm along the gripper z axis, and the bellows cup rides on it (``add_cup``), its
    rim centre (site ``RIM_SITE``) at the gripper site when at rest. Returns the cup's body (the welds' first
    body)."""
    for ex in list(hand.contact.exclude):  # each one excludes a finger's contacts with the palm
        ex.remove()
    for f in (1, 2, 3):
        hand.find("actuator", f"finger_{f}").remove()
        hand.find("body", f"b_finger_{f}").remove()
    return add_cup(hand.find("body", "hand"), T_hand_gripper, tool_cylinders(cfg)[0], cfg)


def add_cup(parent: mjcf.Element, T_parent_rim: np.ndarray, stem: ToolCylinder, cfg: SuctionConfig) -> mjcf.Element:
    """The cup on body ``parent``: geom ``STEM_GEOM`` (``stem``, from the rim at rest along its z axis) and the
    bellows cup (body ``CUP_BODY``) on a slide joint along that axis (range [-stroke, 0], a spring and damper
    holding it at 0), its rim centre (site ``RIM_SITE``) at ``T_parent_rim`` at rest. Returns the cup's body."""
    _, cup = tool_cylinders(cfg)
    R, quat = T_parent_rim[:3, :3], R_to_quat(T_parent_rim[:3, :3])
    mid = T_parent_rim[:3, 3] + 0.5 * (stem.z0 + stem.z1) * R[:, 2]
    parent.add("geom", name=STEM_GEOM, type="cylinder", size=(stem.radius, 0.5 * (stem.z1 - stem.z0)), pos=mid,
               quat=quat, mass=STEM_MASS, rgba=_STEEL, **_HAND_CONTACT)
    body = parent.add("body", name=CUP_BODY, pos=T_parent_rim[:3, 3], quat=quat)
    body.add("joint", name=SLIDE_JOINT, type="slide", axis=(0, 0, 1), range=(-cfg.stroke, 0.0), limited="true",
             stiffness=BELLOWS_STIFFNESS, springref=0.0, damping=BELLOWS_DAMPING, armature=0.001, frictionloss=0.0)
    body.add("geom", name=BELLOWS_GEOM, type="cylinder", size=(cup.radius, 0.5 * (cup.z1 - cup.z0)),
             pos=(0.0, 0.0, 0.5 * (cup.z0 + cup.z1)), mass=CUP_MASS, rgba=_RUBBER, **_HAND_CONTACT)
    body.add("site", name=RIM_SITE, size=(0.003,), group=4)
    return body


def add_welds(spec: mujoco.MjSpec, cup: str, n_parts: int) -> None:
    """One weld per part ``block_k`` (k = 1..n_parts) to the cup's body (its name ``cup``), switched off until a
    seal; the relative pose is taken at compile time (a zero quaternion in the weld's data), as MJCF's default."""
    for k in range(1, n_parts + 1):
        spec.add_equality(type=mujoco.mjtEq.mjEQ_WELD, objtype=mujoco.mjtObj.mjOBJ_BODY, name=weld_name(k),
                          name1=cup, name2=f"block_{k}", active=False, data=[0.0] * 10 + [1.0, 0.0],
                          solref=WELD_SOLREF, solimp=WELD_SOLIMP)


# -- seal ---------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SealCheck:
    """Does the rim seal (``sealed``); ``margin`` (m): ``seal_tolerance`` less the worst rim point's distance from
    the part's surface along the approach axis (>= 0 seals; -inf: a point has no surface under it); ``reason``:
    why it does not seal ("" when it does)."""

    sealed: bool
    margin: float
    reason: str


def _surface_offsets(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Per point (n, 2: x, y in the cup frame), the height z (m, cup frame: positive ahead of the rim) of the nearest
    triangle (m, 3, 3; cup frame) on the line through it along z whose outside looks back at the cup (inf: none)."""
    lo, hi = tri[:, :, :2].min(axis=1), tri[:, :, :2].max(axis=1)
    reach = np.abs(points).max()
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    nz = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]  # the outward normal's z component (times twice the area)
    keep = (nz < -1e-12) & np.all(lo <= reach, axis=1) & np.all(hi >= -reach, axis=1)
    a, e1, e2, nz = a[keep], e1[keep], e2[keep], nz[keep]
    d = points[:, None, :] - a[None, :, :2]  # (n, m, 2)
    u = (d[..., 0] * e2[:, 1] - d[..., 1] * e2[:, 0]) / nz  # barycentric coordinates of the point in the triangle
    v = (e1[:, 0] * d[..., 1] - e1[:, 1] * d[..., 0]) / nz
    z = np.where((u >= 0.0) & (v >= 0.0) & (u + v <= 1.0), a[:, 2] + u * e1[:, 2] + v * e2[:, 2], np.inf)
    if not z.shape[1]:
        return np.full(len(points), np.inf)
    return np.take_along_axis(z, np.argmin(np.abs(z), axis=1)[:, None], axis=1)[:, 0]


def seal_on_mesh(vertices: np.ndarray, faces: np.ndarray, T_world_obj: np.ndarray, T_world_cup: np.ndarray,
                 cfg: SuctionConfig) -> SealCheck:
    """The seal of a cup at ``T_world_cup`` (cup frame) on a part's surface: ``vertices`` (N, 3) m and
    outward-facing ``faces`` (M, 3) in the object frame, the object at ``T_world_obj``. Each of ``RIM_POINTS`` rim
    points must find the surface along the approach axis within ``cfg.seal_tolerance`` of the rim."""
    T = invert(np.asarray(T_world_cup, dtype=float)) @ np.asarray(T_world_obj, dtype=float)  # T_cup_obj
    tri = (np.asarray(vertices, dtype=float) @ T[:3, :3].T + T[:3, 3])[np.asarray(faces)]
    h = _surface_offsets(rim_points(cfg)[:, :2], tri)
    tol = cfg.seal_tolerance
    worst = float(np.abs(h).max())
    missing = int(np.isinf(h).sum())
    if missing:
        return SealCheck(False, -math.inf, f"{missing} of {len(h)} rim points have no surface under them "
                                           "(off an edge or over a hole)")
    if h.min() > tol:
        return SealCheck(False, tol - worst, f"the rim does not touch the part ({h.min() * 1e3:.1f} mm above it)")
    if h.max() < -tol:
        return SealCheck(False, tol - worst, f"the rim lies inside the part ({-h.max() * 1e3:.1f} mm deep)")
    if worst > tol:
        return SealCheck(False, tol - worst, f"the surface under the rim is not flat: it lies {h.min() * 1e3:+.1f} "
                                             f"to {h.max() * 1e3:+.1f} mm off the rim (tolerance "
                                             f"{tol * 1e3:.1f} mm: studs, a step, an edge or a curve)")
    return SealCheck(True, tol - worst, "")


def cup_pose(wc: Workcell) -> np.ndarray:
    """``T_world_cup``: the rim centre's frame (the gripper frame moved with the bellows)."""
    s = wc.model.site(f"jaco_arm/jaco_hand/{RIM_SITE}").id
    return make_T(wc.data.site_xmat[s].reshape(3, 3), wc.data.site_xpos[s])


def seal_check(wc: Workcell, k: int, T_world_cup: np.ndarray | None = None) -> SealCheck:
    """The seal of a cup at ``T_world_cup`` (default: where the cup is now, ``cup_pose``) on part ``k`` (1-based, as
    ``Workcell.blocks``) at its true pose, with the workcell's ``SuctionConfig``."""
    part = wc.blocks[k - 1].block
    T = cup_pose(wc) if T_world_cup is None else T_world_cup
    return seal_on_mesh(part.vertices, part.faces, wc.block_poses()[k - 1], T, wc.cfg.suction)


# -- hold ---------------------------------------------------------------------------------------------------------
def vacuum_force(cfg: SuctionConfig, dp: float | None = None) -> float:
    """The vacuum's pull (N) on a sealed part: the pressure difference ``dp`` (Pa; default the full vacuum) times
    the rim's area."""
    dp = 1e3 * cfg.vacuum_kpa if dp is None else dp
    return dp * math.pi * rim_radius(cfg) ** 2


def _evacuation_time(cfg: SuctionConfig) -> float:
    """Time constant (s) of the pump emptying cup and hose: their volume over its flow."""
    volume = math.pi * rim_radius(cfg) ** 2 * cup_height(cfg) + HOSE_VOLUME
    return volume / (cfg.flow_lpm / 60e3)


def seal_time(cfg: SuctionConfig) -> float:
    """Time (s) from a seal to the full vacuum: the pump's flow ``Q`` empties cup and hose (volume ``V``) as
    ``dp(t) = p0 (1 - exp(-t Q / V))`` until it reaches ``vacuum_kpa`` below ambient ``p0``."""
    return _evacuation_time(cfg) * math.log(AMBIENT_KPA / (AMBIENT_KPA - cfg.vacuum_kpa))


def pressure_at(cfg: SuctionConfig, t: float) -> float:
    """The vacuum (Pa below ambient) ``t`` s after a seal (``seal_time``)."""
    p0 = 1e3 * AMBIENT_KPA
    return min(1e3 * cfg.vacuum_kpa, p0 * (1.0 - math.exp(-max(t, 0.0) / _evacuation_time(cfg))))


def _share(load: float, capacity: float) -> float:
    """``load / capacity``: 0 without a load, inf without a capacity."""
    return 0.0 if load <= 0.0 else load / capacity if capacity > 0.0 else math.inf


def load_ratio(force: np.ndarray, torque: np.ndarray, cfg: SuctionConfig, dp: float | None = None
               ) -> tuple[float, str]:
    """How much of what a sealed cup resists a load takes: the cup's force (N) and torque (N m, about the rim
    centre) on the part in the cup frame, under the vacuum ``dp`` (Pa; default the full one). Held below 1.

    With the vacuum's pull ``V = dp pi r^2``, safety factor ``s``, rim friction ``mu``, the tension ``f_n = -f_z``
    (the cup pulling the part toward itself), the rim's press ``V - f_n``: pull-off ``s (f_n + |t_xy| / r) / V``
    (a moment peels the rim off over its radius: a hanging part ``m (g + a) (1 + d / r)`` with its centre of mass
    ``d`` off the axis), shear ``s |f_xy| / (mu (V - f_n))`` and twist ``s |t_z| / (mu r (V - f_n))``; the largest
    one, with a line saying which."""
    V, s, mu, r = vacuum_force(cfg, dp), cfg.safety, cfg.friction, rim_radius(cfg)
    f, t = np.asarray(force, dtype=float), np.asarray(torque, dtype=float)
    tension, peel = -f[2], float(np.hypot(t[0], t[1])) / r
    press = V - tension
    modes = {"pull-off": _share(s * (tension + peel), V),
             "shear": _share(s * float(np.hypot(f[0], f[1])), mu * press),
             "twist": _share(s * abs(t[2]), mu * r * press)}
    worst = max(modes, key=modes.get)
    kpa = cfg.vacuum_kpa if dp is None else dp / 1e3
    text = (f"{worst} {modes[worst]:.2f} of what {kpa:.1f} kPa on a {1e3 * cfg.diameter:.0f} mm cup holds "
            f"(tension {tension:.2f} N, moment {np.hypot(t[0], t[1]):.3f} N m, shear {np.hypot(f[0], f[1]):.2f} N, "
            f"twist {abs(t[2]):.3f} N m, safety {s:g})")
    return float(modes[worst]), text


def hanging_load(mass: float, p_com: np.ndarray, T_world_cup: np.ndarray, accel: np.ndarray = np.zeros(3)
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The cup's force (N) and torque (N m, about the rim centre) in the cup frame on a part of ``mass`` kg with its
    centre of mass at ``p_com`` (m, world) that hangs still on it, or moves with it at ``accel`` (m/s^2, world)
    without turning: for a planner's ``load_ratio`` before the pick."""
    F = mass * (np.asarray(accel, dtype=float) - GRAVITY)
    tau = np.cross(np.asarray(p_com, dtype=float) - T_world_cup[:3, 3], F)
    R = T_world_cup[:3, :3]
    return R.T @ F, R.T @ tau


@dataclass(frozen=True)
class HoldCheck:
    """After ``Vacuum.check``: is ``part`` (1-based; 0: none) ``held``; ``load``: ``load_ratio`` of the cup's load
    (held below 1); ``reason``: why it is not held ("" when it is)."""

    held: bool
    part: int
    load: float
    reason: str


_CONTACT_ROWS = (mujoco.mjtConstraint.mjCNSTR_CONTACT_FRICTIONLESS, mujoco.mjtConstraint.mjCNSTR_CONTACT_PYRAMIDAL,
                 mujoco.mjtConstraint.mjCNSTR_CONTACT_ELLIPTIC)


class Vacuum:
    """The vacuum of a workcell with a cup (``hand = "suction"`` or ``"hybrid"``), switched by a controller:
    ``on(k)`` seals on part ``k`` where ``seal_check`` passes, ``check()`` each control period releases the part
    when the hold model says the vacuum lets go, ``off()`` releases it. ``part``: the part held (1-based; 0: none)."""

    def __init__(self, wc: Workcell):
        if wc.cfg.hand not in CUP_HANDS:
            raise ConfigError(f"a vacuum needs workcell hand 'suction' or 'hybrid', not {wc.cfg.hand!r}")
        m = wc.model
        self.wc, self.cfg = wc, wc.cfg.suction
        self.cup_body = m.body(f"jaco_arm/jaco_hand/{CUP_BODY}").id
        self.cup_geoms = np.flatnonzero(m.geom_bodyid == self.cup_body)
        self.welds = np.array([m.equality(weld_name(k)).id for k in range(1, len(wc.blocks) + 1)], dtype=int)
        self.part = 0
        self.sealed_at = 0.0  # simulated time (s) of the seal
        self.reason = "vacuum off"  # why no part is held

    @property
    def holding(self) -> bool:
        """Is a part held (sealed and welded; a workcell reset lets go)?"""
        return bool(self.part) and bool(self.wc.data.eq_active[self.welds[self.part - 1]])

    def pressure(self) -> float:
        """The vacuum (Pa below ambient) in the cup now: 0 holding nothing, rising to the full one over
        ``seal_time`` after the seal."""
        return pressure_at(self.cfg, float(self.wc.data.time) - self.sealed_at) if self.holding else 0.0

    def on(self, k: int) -> SealCheck:
        """Switch the vacuum on with the cup on part ``k`` (1-based): where the rim seals on it, as it lies now, the
        part is held from now on (the vacuum builds over ``seal_time``); else nothing is, and the check says why."""
        self.off()
        seal = seal_check(self.wc, k)
        if not seal.sealed:
            self.reason = f"no seal on part {k}: {seal.reason}"
            return seal
        m, d, eq, body = self.wc.model, self.wc.data, self.welds[k - 1], self.wc.block_body[k - 1]
        T_cup_part = invert(make_T(d.xmat[self.cup_body].reshape(3, 3), d.xpos[self.cup_body])) \
            @ make_T(d.xmat[body].reshape(3, 3), d.xpos[body])
        m.eq_data[eq, :3] = 0.0  # anchor: the part's origin, held at its pose in the cup's frame now
        m.eq_data[eq, 3:6] = T_cup_part[:3, 3]
        m.eq_data[eq, 6:10] = R_to_quat(T_cup_part[:3, :3])
        d.eq_active[eq] = 1
        self.part, self.sealed_at, self.reason = k, float(d.time), ""
        return seal

    def off(self) -> None:
        """Switch the vacuum off: the part held, if any, is let go at once."""
        if self.part:
            self.wc.data.eq_active[self.welds[self.part - 1]] = 0
        self.part, self.reason = 0, "vacuum off"

    def _on_cup(self, k: int) -> np.ndarray:
        """(ncon, 2) bool, per contact of the last physics step and side: a cup geom against part ``k`` (1-based)."""
        d = self.wc.data
        g = d.contact.geom[:d.ncon]
        return np.isin(g, self.cup_geoms) & (self.wc.model.geom_bodyid[g[:, ::-1]] == self.wc.block_body[k - 1])

    def touches(self, k: int) -> bool:
        """Does the cup touch part ``k`` (1-based; contacts of the last physics step)?"""
        return bool(self._on_cup(k).any())

    def load(self) -> tuple[np.ndarray, np.ndarray]:
        """The cup's force (N) and torque (N m, about the rim centre) on the held part in the cup frame, from the
        last physics step: its weld's constraint force and its contacts with the cup (zero holding nothing)."""
        if not self.holding:
            return np.zeros(3), np.zeros(3)
        m, d, k = self.wc.model, self.wc.data, self.part
        body, n = self.wc.block_body[k - 1], d.nefc
        rows = (d.efc_type[:n] == mujoco.mjtConstraint.mjCNSTR_EQUALITY) & (d.efc_id[:n] == self.welds[k - 1])
        if d.ncon:
            pair = np.flatnonzero(self._on_cup(k).any(axis=1))
            rows |= np.isin(d.efc_type[:n], _CONTACT_ROWS) & np.isin(d.efc_id[:n], pair)
        qfrc = np.zeros(m.nv)
        mujoco.mj_mulJacTVec(m, d, qfrc, np.where(rows, d.efc_force[:n], 0.0))
        dof = m.jnt_dofadr[m.body_jntadr[body]]  # a free joint: world force, body-frame torque about its origin
        F, R_body = qfrc[dof:dof + 3], d.xmat[body].reshape(3, 3)
        T = cup_pose(self.wc)
        tau = R_body @ qfrc[dof + 3:dof + 6] + np.cross(d.xpos[body] - T[:3, 3], F)
        return T[:3, :3].T @ F, T[:3, :3].T @ tau

    def check(self) -> HoldCheck:
        """The hold model on the held part, after a control period: its ``load_ratio`` under the vacuum now; over 1
        the seal is lost and the part let go (``reason`` says why)."""
        k = self.part
        if not self.holding:
            if k:
                self.part, self.reason = 0, "let go (the workcell was reset)"
            return HoldCheck(False, 0, 0.0, self.reason)
        ratio, why = load_ratio(*self.load(), self.cfg, self.pressure())
        if ratio > 1.0:
            self.off()
            self.reason = f"seal lost on part {k}: {why}"
            return HoldCheck(False, k, ratio, self.reason)
        return HoldCheck(True, k, ratio, "")
