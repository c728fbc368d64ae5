"""Bin picking into a tray (``place = "tray"``): each picked part is set down in a free slot of its type at the
slot's pose, and judged there.

The goal pose of a part (world, model frame): resting on the plate on the face whose outward normal ``n`` (object
frame, a face of its convex hull that it can stand on) lies nearest the tool's approach direction as it holds the
part (the face the tool came down on stays up, and the tool is set down nearest upright), turned about the vertical
by the slot's yaw::

    R_goal = Rz(yaw_slot) R_n,    R_n n = -z  (the least rotation that does it),
    p_goal = (x_slot, y_slot, z_plate - min_v (R_goal v)_z).

The hand sets it down holding it as the estimate at the pick says it holds it: the gripper's release pose is ``T_goal
T_gripper_obj^-1`` with ``T_gripper_obj = T_world_gripper^-1 T_world_obj`` at the grasp, the goal taken over the part's
symmetries ``T_goal S`` as the one the wrist turns least to among those the arm reaches, raised where the hand would
reach below the plate (``hand_below``). The fingers' grip is locked
from the lift on (``ArmController.lock_grip``), so the part does not creep in them. With the tray's ``second_look`` the
hand first holds the part over the tray's upward camera (``sim.tray``) and the provider estimates it there:
``T_gripper_obj = T_world_gripper^-1 T_world_cam T_cam_obj`` of the estimate of the part's type nearest (over the part's
symmetries) to where the pick's estimate puts it, within ``LOOK_GATE``; without one, or without asking the provider
(``look_provider`` false), and with ``look_fit``, the pose the pick's estimate gives the part, shifted onto the look's
depth image less the hand's own surface (``perception.held``, ``sim.robot_surface``) and, with the fit's ``turn_deg``,
turned about the vertical to its seen outline, within the gate; else the
pick's stands. The verdict (the simulator's truth) on the part at rest, modulo its symmetries (``PlaceError``): its face
within ``face_tol_deg`` of the planned one (else "wrong face up"), its origin within ``pos_tol`` (xy) of the slot (else
"misplaced", as for a part of another type than the slot's), its yaw within ``yaw_tol_deg`` (else "misaligned").
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np
from scipy.spatial import ConvexHull

from posegrasp.catalog import PartType, catalog_by_id, set_root
from posegrasp.errors import ConfigError
from posegrasp.geometry import make_T, transform_points
from posegrasp.grasping.perception import PerceptionError, observation
from posegrasp.grasping.record import Failure
from posegrasp.grasping.targets import Plan, reach_q
from posegrasp.grasping.tasks.base import EpisodeFailed
from posegrasp.grasping.tasks.bin_pick.config import HELD_LOOK, BinPickConfig
from posegrasp.grasping.tasks.bin_pick.planner import CUP_SETTLE_SPEED, CUP_SETTLE_TIME
from posegrasp.grasping.upright import match, symmetries
from posegrasp.perception.held import HeldFit, HeldFitConfig
from posegrasp.sim.config import CameraConfig, WorkcellConfig
from posegrasp.sim.robot_surface import hand_points
from posegrasp.sim.tray import PART_CAMERA, TRAY, Tray
from posegrasp.sim.workcell import Workcell

if TYPE_CHECKING:
    from posegrasp.grasping.config import GraspConfig, TrialConfig
    from posegrasp.grasping.episode import Episode

DOWN = np.array([0.0, 0.0, -1.0])
#: The hand stops this far (m) above its release pose, where the arm's settled offset is measured and taken out.
NEAR = 0.008
#: The second look's estimate is taken when it lies within this distance (m) and angle (deg) of where the pick's
#: estimate puts the held part: a part shifts a few millimetres in closing fingers, not more.
LOOK_GATE = (0.02, 20.0)
#: Seeds of the second looks: ``Episode.seed_for(LOOK_SEEDS + attempt)``, apart from the looks into the tote.
LOOK_SEEDS = 1_000_000


#: A part rests stably on a face that tipping over one of its edges takes this much (deg) to: ``atan(d / h)``, the
#: centre of mass ``h`` (m) above the face and its foot ``d`` inside the nearest edge (a brick's studs' slope: 6.6).
MIN_TIP_DEG = 10.0


@functools.lru_cache(maxsize=64)
def rest_normals(block: PartType) -> np.ndarray:
    """(F, 3) outward unit normals (object frame) of the convex hull's faces the part rests on stably: tipping it
    over takes ``MIN_TIP_DEG`` or more, or the face runs along a continuous symmetry axis (a lying cylinder's sides
    roll into one another)."""
    v = np.asarray(block.vertices, float)
    hull = ConvexHull(v)
    com = centre_of_mass(block)
    axes = [np.asarray(a, float) for a, _ in block.symmetries_continuous]
    out: list[np.ndarray] = []
    for eq in np.unique(np.round(hull.equations, 6), axis=0):
        n, d = eq[:3] / np.linalg.norm(eq[:3]), eq[3]
        on = v[np.abs(v @ n + d) < 1e-6]  # the face's vertices
        if len(on) < 3:
            continue
        h = -(com @ n + d)  # the centre of mass's height above the face
        inside = _edge_distance(com + h * n, on, n)
        if inside > 1e-4 and (any(abs(n @ a) < 1e-6 for a in axes) or np.degrees(np.arctan2(inside, h)) >= MIN_TIP_DEG):
            out.append(n)
    return np.array(out)


def centre_of_mass(block: PartType) -> np.ndarray:
    """The solid's centre of mass (m, object frame) at uniform density: the volume-weighted centroids of the
    tetrahedra its faces span with the origin."""
    a, b, c = (block.vertices[block.faces[:, i]] for i in range(3))
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    return (vol[:, None] * (a + b + c) / 4.0).sum(axis=0) / vol.sum()


def _edge_distance(p: np.ndarray, pts: np.ndarray, n: np.ndarray) -> float:
    """How far (m) ``p`` lies inside the convex polygon of the coplanar ``pts`` (normal ``n``); negative: outside."""
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    hull = ConvexHull(np.stack([pts @ u, pts @ w], axis=1))
    return float(-np.max(hull.equations[:, :2] @ np.array([p @ u, p @ w]) + hull.equations[:, 2]))


def align_down(n: np.ndarray) -> np.ndarray:
    """The least rotation taking the unit vector ``n`` onto straight down (-z)."""
    axis = np.cross(n, DOWN)
    s, c = np.linalg.norm(axis), float(n @ DOWN)
    if s < 1e-9:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


def rest_face(block: PartType, down: np.ndarray) -> np.ndarray:
    """The rest face's outward normal (object frame) nearest the object-frame direction ``down``."""
    normals = rest_normals(block)
    return normals[int(np.argmax(normals @ down))]


def goal_pose(block: PartType, n: np.ndarray, xy: np.ndarray, yaw: float, z_plate: float) -> np.ndarray:
    """``T_world_obj`` of the part resting on face ``n`` on a plate at height ``z_plate``, its model origin over
    ``xy`` and turned ``yaw`` (rad) about the vertical."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ align_down(n)
    z = z_plate - float((block.vertices @ R.T)[:, 2].min())
    return make_T(R, (xy[0], xy[1], z))


def goal_copies(block: PartType, n: np.ndarray, xy: np.ndarray, yaw: float, z_plate: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """The goal pose (``goal_pose``) as (K, 4, 4) copies ``T_goal S^-1`` over the part's symmetries ``S`` (one
    physical pose), with (K, 3) the rest face's normal in each copy's model frame, ``R_S n`` (the face down in it)."""
    syms = symmetries(block)
    return goal_pose(block, n, xy, yaw, z_plate)[None] @ np.linalg.inv(syms), syms[:, :3, :3] @ n


def release_choice(wc: Workcell, g_cfg: GraspConfig, releases: np.ndarray, T_lift: np.ndarray, above: float) -> int:
    """Index of the release pose (world gripper, (N, 4, 4): one per symmetric copy of the goal) to set a part down
    from. The copies place the part alike but hold it from different sides: of those whose tool points down the
    most (a cube's turned about the vertical; not an L's flipped onto its other leg, whose tool would lie on its
    side), the one the wrist turns least to from ``T_lift`` among those the arm's IK reaches, with the pose ``above``
    (m) over it (``targets.reach_q``); the least turn of them where it reaches none."""
    down = -releases[:, 2, 2]  # cosine of the tool's approach axis with straight down
    turn = np.einsum("ji,nji->n", T_lift[:3, :3], releases[:, :3, :3])  # trace(R_lift^T R): larger, less turn
    order = [int(i) for i in np.argsort(-turn, kind="stable") if down[i] > down.max() - 1e-3]
    return next((i for i in order if reach_q(wc, g_cfg, releases[i], above) is not None), order[0])


def hand_below(wc: Workcell, T_release: np.ndarray, z_plate: float) -> float:
    """How far (m) the hand, holding the part as it holds it now, would reach below the plate's top ``z_plate`` at
    the release pose ``T_release`` (world gripper); 0 where it stays above. A pinch tilted in the tote can hold a
    part with its lower fingertip below the part's bottom: the part is let go that much higher, not pushed into the
    plate by the finger."""
    pts = transform_points(np.linalg.inv(wc.gripper_pose()), hand_points(wc))  # gripper frame
    return max(0.0, z_plate - float(transform_points(T_release, pts)[:, 2].min()))


@dataclass(frozen=True)
class PlaceError:
    """A placed part against its slot's goal, modulo the part's symmetries: xy distance and height difference of
    the model origins (m), yaw about the vertical and tilt of the resting face (deg)."""

    te: float
    dz: float
    yaw_deg: float
    tilt_deg: float

    def to_json(self) -> dict:
        return {"te": self.te, "dz": self.dz, "yaw_deg": self.yaw_deg, "tilt_deg": self.tilt_deg}


def place_error(block: PartType, T_final: np.ndarray, T_goal: np.ndarray, n: np.ndarray) -> PlaceError:
    """The final pose ``T_final`` (world) against ``T_goal``, over the part's symmetries (the copy whose rotation is
    nearest the goal's); ``n`` the planned rest face's normal (object frame)."""
    copies = T_final @ symmetries(block)
    i, _, _ = match(copies, T_goal[None])
    T = copies[i]
    M = T[:3, :3] @ T_goal[:3, :3].T
    yaw = float(np.degrees(np.arctan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1])))
    tilt = float(np.degrees(np.arccos(np.clip(-(T[:3, :3] @ n)[2], -1.0, 1.0))))
    d = T[:3, 3] - T_goal[:3, 3]
    return PlaceError(float(np.hypot(d[0], d[1])), float(d[2]), yaw, tilt)


def verdict(err: PlaceError, right_type: bool, b: BinPickConfig) -> Failure | None:
    """The placement's failure reason (None: placed within the tolerances)."""
    if err.tilt_deg > b.face_tol_deg:
        return Failure.WRONG_FACE
    if not right_type or err.te > b.pos_tol:
        return Failure.MISPLACED
    if abs(err.yaw_deg) > b.yaw_tol_deg:
        return Failure.MISALIGNED
    return None


@dataclass
class Placing:
    """A part on its way to slot ``slot``: the goal pose (world) and the rest face's normal (object frame)."""

    slot: int
    T_goal: np.ndarray
    n: np.ndarray
    in_hand: dict | None = None  # the second look's change to the held pose: shift (m), turn (deg); None: no look


class TrayPlace:
    """The tray of an episode: which slots the robot has filled, where it sets each part down, and the verdict."""

    parks, keeps_pose = False, True  # placed parts stay in their slots, at the pose they were set down

    def __init__(self, ep: Episode, tray: Tray):
        self.ep, self.tray = ep, tray
        self.filled = [False] * len(tray.cfg.slots)
        self.placing: Placing | None = None
        m = ep.wc.model
        self.plate = m.geom(f"{TRAY}/plate").id

    @property
    def top_z(self) -> float:
        return self.tray.top_z

    def holds(self, T_world_obj: np.ndarray, block: PartType) -> bool:
        """The part's vertex centroid over the plate (within 5 mm) and above its top."""
        return bool(self.tray.holds(transform_points(T_world_obj, block.vertices).mean(axis=0)[None], 0.005)[0])

    def free(self, type_name: str) -> int | None:
        """The first free slot of part type ``type_name`` (None: none left)."""
        return next((i for i, (s, f) in enumerate(zip(self.tray.cfg.slots, self.filled))
                     if not f and s.type == type_name), None)

    def deliver(self, plan: Plan, T_lift: np.ndarray, T_hold: np.ndarray, let_go: Callable[[], None]) -> None:
        """Carry the part held at gripper pose ``T_hold`` (at the grasp) from ``T_lift`` over its slot (by the
        second look, if the tray has one), set it down there at the goal pose (the hand stops early where the part
        or the hand touches the plate or another part) and let go (``let_go``: the tool's release), then raise the
        hand; the slot counts as filled once the part is let go over it."""
        ep, b = self.ep, self.ep.cfg.bin_pick
        ctl, g_cfg, block = ep.ctl, ep.cfg.grasp, plan.est_block or plan.block
        slot = self.free(block.name)
        if slot is None:  # the planner only goes for parts with a free slot
            raise EpisodeFailed(Failure.NO_SLOT)
        xy, yaw = self.tray.slot_pose(slot)
        T_obj_gripper, in_hand = np.linalg.inv(plan.T_world_obj) @ T_hold, None
        ctl.lock_grip()  # the part is set down as held now (or as the look sees it): it must not creep after
        if self.tray.cfg.second_look:
            T_obj_gripper, in_hand = self._second_look(block, T_obj_gripper, T_lift)
        n = rest_face(block, T_obj_gripper[:3, 2])  # the face the tool came down on stays up
        goals, normals = goal_copies(block, n, xy, yaw, self.top_z)
        i = release_choice(ep.wc, g_cfg, goals @ T_obj_gripper, T_lift, b.place_gap + g_cfg.pregrasp_height)
        T_goal, T_release = goals[i], goals[i] @ T_obj_gripper
        self.placing = Placing(slot, T_goal, normals[i], in_hand)
        T_release[2, 3] += b.place_gap + hand_below(ep.wc, T_release, self.top_z)
        T_above = T_release.copy()
        T_above[2, 3] = max(T_lift[2, 3], T_release[2, 3] + g_cfg.pregrasp_height)
        ctl.move(T_above, speed=g_cfg.carry_speed, reposture=True)  # a tilted set-down: held off by the posture term
        ctl.settle(CUP_SETTLE_SPEED, CUP_SETTLE_TIME)  # the arm sways after the carry: still, then down
        touches = functools.partial(self._touches, plan.k)
        T_near = T_release.copy()
        T_near[2, 3] += NEAR
        ctl.move(T_near, speed=g_cfg.approach_speed, until=touches)
        off = ctl.null_offset(T_near, CUP_SETTLE_SPEED, CUP_SETTLE_TIME, until=touches)
        T_down = T_release.copy()
        T_down[:2, 3] += off
        ctl.move(T_down, speed=g_cfg.approach_speed, until=touches)
        ctl.settle(CUP_SETTLE_SPEED, CUP_SETTLE_TIME)
        ep.log.stop("carry", ctl, add=True)
        let_go()
        self.filled[slot] = True
        T_up = ctl.target.copy()
        T_up[2, 3] += g_cfg.pregrasp_height
        ctl.move(T_up)
        ep.log.stop("place", ctl, add=True)

    def _second_look(self, block: PartType, T_obj_gripper: np.ndarray, T_lift: np.ndarray
                     ) -> tuple[np.ndarray, dict]:
        """Hold the part (held as ``T_obj_gripper`` says) over the upward camera, its estimated centre the tray's
        ``look_height`` above it, the hand turned as at ``T_lift``; capture and ask the provider. Returns the held
        pose ``T_obj_gripper`` the look sees (the one given where it sees none within ``LOOK_GATE``) and the change
        (shift m, turn deg; ``seen``: whether the look's estimate was taken)."""
        ep, cfg = self.ep, self.tray.cfg
        ctl, wc = ep.ctl, ep.wc
        T_world_cam = wc.camera_pose(self.camera)
        centre = 0.5 * (block.vertices.min(0) + block.vertices.max(0))
        T_show = T_lift.copy()
        held = T_show[:3, :3] @ np.linalg.inv(T_obj_gripper)[:3, :] @ np.append(centre, 1.0)  # centre - gripper
        T_show[:3, 3] = T_world_cam[:3, 3] + (0.0, 0.0, cfg.look_height) - held
        ctl.move(T_show, speed=ep.cfg.grasp.carry_speed)
        ctl.settle(CUP_SETTLE_SPEED, CUP_SETTLE_TIME)
        ep.log.stop("look in hand", ctl, add=True)
        a = len(ep.rec.attempts)
        fovy = float(wc.model.cam_fovy[wc.camera_ids[self.camera]])
        c = wc.cfg.hand_camera  # its image size, the model's field of view, depth from 5 cm
        frame = ep.capture(HELD_LOOK + a, True, self.camera, CameraConfig(c.width, c.height, fovy, near=0.05, far=1.0))
        ests = []
        if cfg.look_provider:
            try:
                ests = ep.perceive(frame, ep.seed_for(LOOK_SEEDS + a), HELD_LOOK + a)
            except PerceptionError:
                pass
        T_world_gripper = wc.gripper_pose()
        T_expect = T_world_gripper @ np.linalg.inv(T_obj_gripper)
        syms = symmetries(block)

        def near(T_cam_obj: np.ndarray) -> tuple[float, float, np.ndarray] | None:
            """The pose's copy (over the symmetries) nearest where the pick put the part, within the gate: (shift m,
            turn deg, T_world_obj); None beyond it."""
            copies = T_world_cam @ T_cam_obj @ syms
            i, _, angle = match(copies, T_expect[None])
            shift, turn = float(np.linalg.norm(copies[i][:3, 3] - T_expect[:3, 3])), float(np.degrees(angle))
            return (shift, turn, copies[i]) if shift <= LOOK_GATE[0] and turn <= LOOK_GATE[1] else None

        best = min((n for e in ests if e.obj_id == block.obj_id and (n := near(e.T_cam_obj)) is not None),
                   key=lambda n: n[0], default=None)
        fitted = best is None and cfg.look_fit
        if fitted:
            fit = _held_fit(wc.cfg.objects, ep.cfg.bin_pick.held_fit)
            T_cam_world = np.linalg.inv(T_world_cam)
            T_cam_fit = fit(block.obj_id, T_cam_world @ T_expect, observation(frame).depth, frame.K,
                            ep.seed_for(LOOK_SEEDS + a), exclude=transform_points(T_cam_world, hand_points(wc)),
                            up=T_cam_world[:3, 2])
            best = None if T_cam_fit is None else near(T_cam_fit)
        if best is None:
            return T_obj_gripper, {"seen": False}
        seen = {"seen": True, "shift": best[0], "turn_deg": best[1]} | ({"fitted": True} if fitted else {})
        return np.linalg.inv(best[2]) @ T_world_gripper, seen

    @property
    def camera(self) -> str:
        """The upward camera's name in the workcell."""
        return f"{TRAY}/{PART_CAMERA}"

    def _touches(self, k: int) -> bool:
        """Do part ``k`` or the robot touch the plate or another part (a tilted hand's lower fingertip can meet the
        plate first)?"""
        wc = self.ep.wc
        d = wc.data
        if not d.ncon:
            return False
        g = d.contact.geom[: d.ncon]
        inst = wc.geom_instance[g]
        mover = (inst == k) | self.ep.ctl.robot_geom[g]
        other = ((g == self.plate) | (inst > 0)) & (inst != k)
        return bool(np.any(mover[:, 0] & other[:, 1]) or np.any(mover[:, 1] & other[:, 0]))

    def judge(self, k: int, block: PartType) -> tuple[PlaceError | None, Failure | None]:
        """The target ``k``'s placement, once at rest, against the goal it was set down for: its error and the
        failure reason (None: placed; "misplaced" when it is not on the tray or was never let go over it)."""
        p, ep = self.placing, self.ep
        if p is None:
            return None, Failure.MISPLACED
        ep.wait_for_rest(k)
        T = ep.wc.block_poses()[k - 1]
        if not self.holds(T, block):
            return None, Failure.MISPLACED
        err = place_error(block, T, p.T_goal, p.n)
        return err, verdict(err, block.name == self.tray.cfg.slots[p.slot].type, ep.cfg.bin_pick)


#: Reach check: the pinch point this high (m) over each slot's plate, the gripper pointing straight down at one of
#: these yaws (deg), within the IK's position (m) and rotation (rad) tolerances.
REACH_HEIGHT, REACH_YAWS, REACH_TOL = 0.03, tuple(range(0, 180, 30)), (0.004, 0.02)


@functools.lru_cache(maxsize=2)
def _held_fit(objects: str, cfg: HeldFitConfig) -> HeldFit:
    """The in-hand fit (settings ``cfg``) of the object set ``objects``'s models, one per worker process."""
    return HeldFit(set_root(objects), cfg)


def check_tray(cfg: TrialConfig, tray: Tray) -> None:
    """A one-line ConfigError unless the tray's slots take the object set's part types without overlapping, hold
    the most parts an episode has, and lie within the arm's reach from above."""
    b = cfg.bin_pick
    radii = {t.name: float(np.linalg.norm(t.vertices, axis=1).max())
             for t in catalog_by_id(cfg.scene.workcell.objects).values()}
    tray.check_layout(radii)
    slots = len(tray.cfg.slots)
    if b.clutter.parts[1] > slots:
        raise ConfigError(f"{b.clutter.parts[1]} parts per episode but the tray has {slots} slots: use --blocks "
                          f"{slots} or fewer, or add [[bin_pick.tray.slots]]")
    bad = unreached_slots(cfg.scene.workcell, tray)
    if bad:
        raise ConfigError(f"the hand cannot reach tray slot(s) {bad} from above (tray centred at "
                          f"{[round(c, 3) for c in tray.center]}): move them, or the tray with bin_pick.tray.offset")
    c = tray.cfg
    look = np.asarray(tray.center) + c.look_camera_xy
    if c.second_look and not reaches(cfg.scene.workcell, (*look, c.look_height + REACH_HEIGHT)):
        raise ConfigError(f"the hand cannot hold a part {c.look_height:g} m over the second look's camera at "
                          f"{[round(float(v), 3) for v in look]} (world): move bin_pick.tray.look_camera_xy nearer "
                          "the arm or lower bin_pick.tray.look_height")


@functools.lru_cache(maxsize=8)
def unreached_slots(workcell: WorkcellConfig, tray: Tray) -> list[int]:
    """The slots (0-based) whose point ``REACH_HEIGHT`` above the plate the gripper, pointing down, reaches at none
    of ``REACH_YAWS``."""
    return [i for i in range(len(tray.cfg.slots))
            if not reaches(workcell, (*tray.slot_pose(i)[0], tray.top_z + REACH_HEIGHT))]


@functools.lru_cache(maxsize=2)
def _arm(workcell: WorkcellConfig) -> Workcell:
    """A bare workcell of these settings, for reach checks by IK."""
    return Workcell(workcell)


@functools.lru_cache(maxsize=64)
def reaches(workcell: WorkcellConfig, point: tuple[float, float, float]) -> bool:
    """Does the gripper, pointing down, reach the world ``point`` (m) at one of ``REACH_YAWS``?"""
    wc = _arm(workcell)
    down = np.diag([1.0, -1.0, -1.0])
    for yaw in np.radians(REACH_YAWS):
        c, s = np.cos(yaw), np.sin(yaw)
        T = make_T(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ down, point)
        _, dp, dr = wc.solve_gripper_ik(T, wc.look_q)
        if dp <= REACH_TOL[0] and dr <= REACH_TOL[1]:
            return True
    return False
