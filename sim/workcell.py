"""The MuJoCo workcell: table, Jaco2 arm with its hand (``sim.robot``), a hand camera, pick and place areas, blocks.

The world (table, lights, cameras, blocks and a scene's extras: a tote, textures) is composed with
``dm_control.mjcf`` (``build_mjcf``); the robot (``sim.robot``) is composed the same way once per process and kept
as a parsed ``mujoco.MjSpec``, attached to each world at compile time (``compile_workcell``): the same model as one
MJCF of both. dm-control's own ``mjcf.Physics`` bindings do not load under MuJoCo 4. World frame: the arm base on
the table top, z up.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable, Sequence

import mujoco
import numpy as np
from dm_control import mjcf

from posegrasp.catalog import PartType
from posegrasp.errors import ConfigError
from posegrasp.geometry import R_to_quat, invert, look_at_R, make_T
from posegrasp.sim.camera import T_CV_MJ, add_mjcf_camera
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.ik import ArmIK
from posegrasp.sim.robot import GRIPPER_SITE, HAND_CAMERA, ROBOT_MOUNT, ROBOT_PREFIX, robot_spec
from posegrasp.sim.suction import add_welds

ARM_JOINTS = tuple(f"joint_{i}" for i in range(1, 7))
FINGER_JOINTS = ("finger_1", "finger_2", "finger_3")
OVERVIEW_CAMERA = "overview"

#: Contact groups: blocks, table and pad collide with everything; visual meshes with nothing.
_COLLIDE = dict(contype=1, conaffinity=1)
_VISUAL = dict(contype=0, conaffinity=0, group=1)
_COLLISION_GROUP = 3
PARKING_Y, PARKING_GAP = 2.0, 0.25  # m: block k waits at (0, PARKING_Y + k PARKING_GAP, 0.5) until placed


@dataclass(frozen=True)
class BlockInstance:
    """One block in a scene: its type, colour (RGBA in [0, 1]) and body name (``block_<k>``, k from 1)."""

    block: PartType
    rgba: tuple[float, float, float, float]


def mesh_file(vertices: np.ndarray, faces: np.ndarray | None = None,
              texcoord: np.ndarray | None = None) -> mjcf.Asset:
    """A mesh as MuJoCo's binary ``.msh`` file in memory: vertices (N, 3) m, faces (F, 3) vertex indices (none: the
    convex hull of the vertices), texture coordinates (N, 2). MuJoCo reads the same float32 values as from the XML
    attributes, without the text a model of many vertices takes to write and parse."""
    v = np.asarray(vertices, np.float32).reshape(-1, 3)
    f = np.zeros((0, 3), np.int32) if faces is None else np.asarray(faces, np.int32).reshape(-1, 3)
    uv = np.zeros((0, 2), np.float32) if texcoord is None else np.asarray(texcoord, np.float32).reshape(-1, 2)
    head = np.array([len(v), 0, len(uv), len(f)], np.int32)
    return mjcf.Asset(head.tobytes() + v.tobytes() + uv.tobytes() + f.tobytes(), ".msh")


def _add_surface(root: mjcf.RootElement, body, k: int, surface) -> None:
    """Geom ``block_k_visual`` drawing a textured surface (``posegrasp.surface.TexturedSurface``, m) in white light."""
    tex = root.asset.add("texture", name=f"block_{k}_texture", type="2d", file=mjcf.Asset(surface.png(), ".png"))
    mat = root.asset.add("material", name=f"block_{k}_material", texture=tex, rgba=(1.0, 1.0, 1.0, 1.0))
    uv = np.column_stack([surface.uv[:, 0], 1.0 - surface.uv[:, 1]])  # MuJoCo's v runs down the image
    mesh = root.asset.add("mesh", name=f"block_{k}_surface", file=mesh_file(surface.vertices, surface.faces, uv),
                          inertia="shell")
    body.add("geom", name=f"block_{k}_visual", type="mesh", mesh=mesh, material=mat, mass=0, **_VISUAL)


#: MuJoCo's default contact time constant (s): soft contacts of the table, the pad and parts ``THIN_PART`` thick or
#: more (the shipped blocks).
CONTACT_TIMECONST = 0.02
#: Impedance of the Jaco's finger contacts (dm-control's model): thin parts' contacts take it too, so that the
#: fingers grip them as hard as the shipped blocks (a domino's edges slip out of MuJoCo's default, 0.9-0.95).
FINGER_SOLIMP = (0.99, 0.999, 0.001, 0.5, 2.0)
#: Parts thinner than this (m) get stiffer contacts (``contact_timeconst``).
THIN_PART = 0.02
#: Fastest a thin part's point moves in a scene's drop (m/s; ``Workcell.cap_thin_speeds``) and the speed its
#: contacts are made for.
CONTACT_SPEED = 1.0


def thickness(vertices: np.ndarray) -> float:
    """Smallest width (m) of a part, vertices (N, 3) m: their extent along the least of their principal axes."""
    v = np.asarray(vertices, dtype=float).reshape(-1, 3)
    v = v - v.mean(axis=0)
    return float(np.ptp(v @ np.linalg.svd(v, full_matrices=False)[2].T, axis=0).min())


@functools.lru_cache(maxsize=64)
def part_timeconst(part: PartType, timestep: float) -> float:
    """``contact_timeconst`` of a part's ``thickness``."""
    return contact_timeconst(thickness(part.vertices), timestep)


def contact_timeconst(width: float, timestep: float) -> float:
    """Contact time constant (s) of a part ``width`` m thin (``thickness``): MuJoCo's default from ``THIN_PART``
    up, else ``e width / (8 CONTACT_SPEED)``, at least three physics steps (stiffer, they jitter and never rest).

    A soft contact of time constant ``tc`` hit at speed ``v`` sinks about ``v tc / e`` before it holds: an
    eighth of the part's width at ``CONTACT_SPEED``. Where it passes half the width, the nearest way out of the
    table (or out of a finger) is through the part's far face: the contact pushes it through the table, or the
    solver blows up (NaN accelerations)."""
    if width >= THIN_PART:
        return CONTACT_TIMECONST
    return float(np.clip(np.e * width / (8.0 * CONTACT_SPEED), 3.0 * timestep, CONTACT_TIMECONST))


def _add_block(root: mjcf.RootElement, k: int, inst: BlockInstance, timestep: float) -> None:
    """A free body ``block_k``: the visual mesh (exactly the PLY model, or the part's textured surface where it
    has one: then the model, carrying the mass, is hidden in the collision group) and the collision primitives;
    those of a thin part with stiffer, harder contacts (``contact_timeconst``, ``FINGER_SOLIMP``) that rule its
    contacts with the table and the hand (``solmix``)."""
    b = inst.block
    mesh = root.asset.add("mesh", name=f"block_{k}_mesh", file=mesh_file(b.vertices, b.faces))
    # parked apart, off the table, until placed: blocks compiled on top of each other and the arm overflow
    # the constraint solver's memory at the first forward pass (a scene of large hulls needed 1470 contacts)
    body = root.worldbody.add("body", name=f"block_{k}", pos=(0.0, PARKING_Y + PARKING_GAP * k, 0.5))
    body.add("freejoint", name=f"block_{k}_joint")
    if b.surface is None:
        body.add("geom", name=f"block_{k}_visual", type="mesh", mesh=mesh, rgba=inst.rgba, mass=b.mass, **_VISUAL)
    else:
        body.add("geom", name=f"block_{k}_solid", type="mesh", mesh=mesh, rgba=(0.5, 0.5, 0.5, 0.0), mass=b.mass,
                 contype=0, conaffinity=0, group=_COLLISION_GROUP)
        _add_surface(root, body, k, b.surface)
    tc = part_timeconst(b, timestep)
    stiff = dict(solref=(tc, 1.0), solimp=FINGER_SOLIMP, solmix=1e3) if tc < CONTACT_TIMECONST else {}
    for j, prim in enumerate(b.collision):
        kw = dict(name=f"block_{k}_col{j}", group=_COLLISION_GROUP, rgba=(0.5, 0.5, 0.5, 0.0), mass=0,
                  friction=(0.9, 0.01, 0.002), condim=6, pos=prim.get("pos", (0, 0, 0)),
                  quat=prim.get("quat", (1, 0, 0, 0)), **_COLLIDE, **stiff)
        if prim["type"] == "mesh":
            hull = root.asset.add("mesh", name=f"block_{k}_hull{j}", file=mesh_file(prim["vertices"]))
            body.add("geom", type="mesh", mesh=hull, **kw)
        else:
            body.add("geom", type=prim["type"], size=prim["size"], **kw)


def build_mjcf(cfg: WorkcellConfig, blocks: Sequence[BlockInstance] = ()) -> mjcf.RootElement:
    """Compose the workcell's world: table, pad, lights, overview camera, blocks, and the body ``ROBOT_MOUNT`` where
    ``compile_workcell`` attaches the robot (``robot_mjcf``). Extras (a tote, textures) go on this root."""
    root = mjcf.RootElement(model="posegrasp_workcell")
    root.option.timestep = cfg.timestep
    root.compiler.angle = "radian"
    cams = (cfg.hand_camera, cfg.overview_camera)
    root.visual.__getattr__("global").offwidth = max(c.width for c in cams)
    root.visual.__getattr__("global").offheight = max(c.height for c in cams)
    root.visual.map.znear = 0.01
    root.visual.map.zfar = 20.0
    root.visual.quality.shadowsize = 2048
    root.statistic.extent = 1.0
    root.statistic.center = (0.3, 0.0, 0.2)

    wb = root.worldbody
    tx, ty, tz = cfg.table_half_size
    wb.add("geom", name="floor", type="plane", size=(3, 3, 0.1), pos=(0, 0, -0.75), rgba=(0.35, 0.35, 0.38, 1))
    wb.add("geom", name="table", type="box", size=(tx, ty, tz), pos=(*cfg.table_center, -tz),
           rgba=(0.62, 0.55, 0.45, 1), friction=(0.9, 0.01, 0.001), **_COLLIDE)
    pad = cfg.place_area
    wb.add("geom", name="place_pad", type="box", size=(*pad.half_size, 0.0015), pos=(*pad.center, 0.0015),
           rgba=(0.15, 0.45, 0.2, 1), friction=(0.9, 0.01, 0.001), **_COLLIDE)
    wb.add("light", name="key", pos=(0.6, -0.4, 1.4), dir=(-0.2, 0.3, -1), diffuse=(0.6, 0.6, 0.6),
           castshadow=cfg.render.shadows)
    wb.add("light", name="fill", pos=(-0.2, 0.6, 1.2), dir=(0.4, -0.4, -1), diffuse=(0.3, 0.3, 0.3),
           castshadow=False)
    T_world_over = make_T(look_at_R(np.subtract(cfg.overview_target, cfg.overview_pos)), cfg.overview_pos)
    add_mjcf_camera(wb, OVERVIEW_CAMERA, T_world_over, cfg.overview_camera)
    wb.add("body", name=ROBOT_MOUNT)
    for k, inst in enumerate(blocks, start=1):
        _add_block(root, k, inst, cfg.timestep)
    return root


def compile_workcell(root: mjcf.RootElement, cfg: WorkcellConfig, n_parts: int) -> mujoco.MjModel:
    """Compile the world ``root`` (``build_mjcf``, with its extras) with the robot of ``cfg`` attached at
    ``ROBOT_MOUNT`` and, with a cup, a weld per part (``suction.add_welds``). The robot is composed and parsed once
    per process (``sim.robot.robot_spec``) and its spec copied: the same model as one MJCF of both, in a fraction
    of the time dm-control takes to build and write the arm, but with MuJoCo's native convex collision, which the
    arm's model turns off: with the older libccd, convex parts landing on each other spin up and sink through a thin
    tote, and a carried part's finger contacts take 2.7x as long."""
    robot, robot_assets, cup = robot_spec(cfg)
    assets = root.get_assets()
    spec = mujoco.MjSpec.from_string(root.to_xml_string(), assets)
    spec.assets, child = assets, robot.copy()  # neither parsing nor copying keeps a spec's mesh files
    child.assets = robot_assets
    spec.attach(child, frame=spec.body(ROBOT_MOUNT).add_frame(), prefix=ROBOT_PREFIX)
    if cup is not None:
        add_welds(spec, cup, n_parts)
    return spec.compile()


def finger_joints(hand: str) -> tuple[str, ...]:
    """The finger joints of ``hand`` (``HANDS``; none on the suction tool, the 2-finger hand's on the hybrid one)."""
    if hand == "suction":
        return ()
    return FINGER_JOINTS if hand == "3-finger" else ("finger_1", "finger_3")


class Workcell:
    """A compiled workcell with named handles: arm and finger joints/actuators, cameras, blocks.

    ``T_world_*`` poses are in the world frame (the arm base on the table top, z up), metres.
    """

    def __init__(self, cfg: WorkcellConfig, blocks: Sequence[BlockInstance] = (),
                 extras: Callable[[mjcf.RootElement], None] | None = None):
        """``extras(root)``, if given, adds items (textures, lights, distractors) to the MJCF before compiling."""
        self.cfg = cfg
        self.blocks = list(blocks)
        self.mjcf_root = build_mjcf(cfg, self.blocks)
        if extras is not None:
            extras(self.mjcf_root)
        self.model = compile_workcell(self.mjcf_root, cfg, len(self.blocks))
        self.data = mujoco.MjData(self.model)
        #: Called with the workcell after every ``step`` (None: nothing); it must not change the physics state.
        self.on_step: Callable[[Workcell], None] | None = None
        #: Called before every ``step`` (None: nothing): what the workcell does meanwhile (the tote's stage shaking).
        self.background: Callable[[], None] | None = None
        m = self.model
        self.arm_joint_names = [f"jaco_arm/{j}" for j in ARM_JOINTS]
        self.finger_joint_names = [f"jaco_arm/jaco_hand/{j}" for j in finger_joints(cfg.hand)]
        #: The number (1-3) of each finger joint's finger.
        self.finger_numbers = np.array([int(n[-1]) for n in self.finger_joint_names], dtype=int)
        self.arm_qadr = np.array([m.joint(n).qposadr[0] for n in self.arm_joint_names])
        self.arm_dadr = np.array([m.joint(n).dofadr[0] for n in self.arm_joint_names])
        self.finger_qadr = np.array([m.joint(n).qposadr[0] for n in self.finger_joint_names], dtype=int)
        self.arm_act = np.array([m.actuator(n).id for n in self.arm_joint_names])
        self.finger_act = np.array([m.actuator(n).id for n in self.finger_joint_names], dtype=int)
        self.gripper_site = m.site(f"jaco_arm/jaco_hand/{GRIPPER_SITE}").id
        self.camera_ids = {HAND_CAMERA: m.camera(f"jaco_arm/jaco_hand/{HAND_CAMERA}").id,
                           OVERVIEW_CAMERA: m.camera(OVERVIEW_CAMERA).id}
        self.camera_ids |= {m.camera(i).name: i for i in range(m.ncam) if i not in self.camera_ids.values()}
        self.block_body = np.array([m.body(f"block_{k}").id for k in range(1, len(self.blocks) + 1)], dtype=int)
        self.block_qadr = np.array([m.joint(f"block_{k}_joint").qposadr[0] for k in range(1, len(self.blocks) + 1)],
                                   dtype=int)
        #: (body id, half diameter m) of the thin blocks, whose contacts are stiffened (``contact_timeconst``).
        self.thin_blocks = [(b, 0.5 * inst.block.diameter) for b, inst in zip(self.block_body, self.blocks)
                            if part_timeconst(inst.block, cfg.timestep) < CONTACT_TIMECONST]
        # geom id -> instance index (0 background / robot / table, k for block_k); used for masks.
        self.geom_instance = np.zeros(m.ngeom + 1, dtype=np.int32)  # last slot: background (-1)
        for k, b in enumerate(self.block_body, start=1):
            self.geom_instance[:-1][m.geom_bodyid == b] = k
        self.reset()

    # -- state ---------------------------------------------------------------------------------------
    def reset(self, arm_q: np.ndarray | None = None) -> None:
        """Reset the simulation with the arm at ``arm_q`` (default: home) and fingers open, at rest."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self.arm_qadr] = self.cfg.home_qpos if arm_q is None else arm_q
        self.data.qpos[self.finger_qadr] = self.model.jnt_range[self._finger_jnt(), 0]
        mujoco.mj_forward(self.model, self.data)

    def _finger_jnt(self) -> np.ndarray:
        return np.array([self.model.joint(n).id for n in self.finger_joint_names], dtype=int)

    @property
    def arm_q(self) -> np.ndarray:
        """Measured arm joint angles (rad)."""
        return self.data.qpos[self.arm_qadr].copy()

    def set_block_pose(self, k: int, T_world_obj: np.ndarray) -> None:
        """Place block ``k`` (1-based) at a world pose, at rest."""
        a = self.block_qadr[k - 1]
        self.data.qpos[a:a + 3] = T_world_obj[:3, 3]
        self.data.qpos[a + 3:a + 7] = R_to_quat(T_world_obj[:3, :3])
        d = self.model.jnt_dofadr[self.model.body_jntadr[self.block_body[k - 1]]]
        self.data.qvel[d:d + 6] = 0.0

    def block_poses(self) -> np.ndarray:
        """``T_world_obj`` of every block, (K, 4, 4)."""
        out = np.tile(np.eye(4), (len(self.blocks), 1, 1))
        for i, b in enumerate(self.block_body):
            out[i, :3, :3] = self.data.xmat[b].reshape(3, 3)
            out[i, :3, 3] = self.data.xpos[b]
        return out

    def cap_thin_speeds(self) -> None:
        """Slow the thin blocks (stiffened contacts, ``contact_timeconst``) whose fastest point (linear speed plus
        spin times half the diameter) moves faster than ``CONTACT_SPEED`` down to it, as air would: dropped from
        high (a scene's parts stacked above each other) or spun by a bounce, they would hit the table faster than
        their contacts hold and sink through it."""
        for b, radius in self.thin_blocks:
            d = self.model.jnt_dofadr[self.model.body_jntadr[b]]
            v = self.data.qvel[d:d + 6]
            fastest = np.linalg.norm(v[:3]) + radius * np.linalg.norm(v[3:])
            if fastest > CONTACT_SPEED:
                v *= CONTACT_SPEED / fastest

    def block_speeds(self) -> np.ndarray:
        """Per block (linear m/s, angular rad/s) speed magnitudes, (K, 2)."""
        out = np.zeros((len(self.blocks), 2))
        for i, b in enumerate(self.block_body):
            d = self.model.jnt_dofadr[self.model.body_jntadr[b]]
            v = self.data.qvel[d:d + 6]
            out[i] = np.linalg.norm(v[:3]), np.linalg.norm(v[3:])
        return out

    def camera_pose(self, name: str = HAND_CAMERA) -> np.ndarray:
        """``T_world_cam`` of a camera in the OpenCV convention (x right, y down, z forward)."""
        i = self.camera_ids[name]
        T_world_mj = make_T(self.data.cam_xmat[i].reshape(3, 3), self.data.cam_xpos[i])
        return T_world_mj @ T_CV_MJ

    def gripper_pose(self) -> np.ndarray:
        """``T_world_gripper``: the pinch site (z along the approach direction)."""
        s = self.gripper_site
        return make_T(self.data.site_xmat[s].reshape(3, 3), self.data.site_xpos[s])

    def T_gripper_cam(self) -> np.ndarray:
        """The true camera mount ``T_gripper_cam`` (OpenCV camera frame), from the model's kinematics."""
        return invert(self.gripper_pose()) @ self.camera_pose(HAND_CAMERA)

    # -- kinematics ----------------------------------------------------------------------------------
    @property
    def ik(self) -> ArmIK:
        """IK on a robot-only copy of this workcell (same arm, hand and camera; no blocks), one per config."""
        return _robot_ik(self.cfg)

    def solve_camera_ik(self, T_world_cam: np.ndarray, q0: np.ndarray | None = None, iters: int = 400):
        """Joint angles placing the hand camera (OpenCV frame) at ``T_world_cam``; with residuals (m, rad)."""
        return self.ik.solve(f"jaco_arm/jaco_hand/{HAND_CAMERA}", T_world_cam @ T_CV_MJ,
                             self.arm_q if q0 is None else q0, iters=iters)

    def solve_gripper_ik(self, T_world_gripper: np.ndarray, q0: np.ndarray | None = None):
        """Joint angles placing the gripper (pinch site) at ``T_world_gripper``; with residuals (m, rad)."""
        return self.ik.solve(f"jaco_arm/jaco_hand/{GRIPPER_SITE}", T_world_gripper, self.arm_q if q0 is None else q0)

    def look_camera_pose(self) -> np.ndarray:
        """``T_world_cam`` of the look pose: above the pick area centre at ``look_height``, looking straight down.

        Image up points away from the arm base (+x), so the pick area fills the frame the long way.
        """
        c = self.cfg.pick_area.center
        R = look_at_R(np.array([0.0, 0.0, -1.0]), up_hint=np.array([1.0, 0.0, 0.0]))
        return make_T(R, (c[0], c[1], self.cfg.look_height))

    @property
    def look_q(self) -> np.ndarray:
        """Arm joint angles of the named look pose (solved from home once per config)."""
        return _look_q(self.cfg).copy()

    # -- control -------------------------------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        """Advance physics ``n`` steps with the current controls (``background`` run first)."""
        if self.background is not None:
            self.background()
        mujoco.mj_step(self.model, self.data, nstep=n)
        if self.on_step is not None:
            self.on_step(self)

    def arm_velocity_limits(self) -> np.ndarray:
        """Joint velocity limits (rad/s) of the arm's velocity actuators."""
        return self.model.actuator_ctrlrange[self.arm_act, 1].copy()

    def command_arm(self, qdot: np.ndarray) -> None:
        """Set the arm's velocity actuators (rad/s), clipped to their limits."""
        lim = self.arm_velocity_limits()
        self.data.ctrl[self.arm_act] = np.clip(qdot, -lim, lim)

    def gravity_feedforward(self) -> np.ndarray:
        """Velocity command offset that makes the velocity actuators cancel gravity and Coriolis terms.

        A velocity actuator applies ``kv (u - qdot)``; adding ``qfrc_bias / kv`` to ``u`` holds the arm still.
        """
        return self.data.qfrc_bias[self.arm_dadr] / self.model.actuator_gainprm[self.arm_act, 0]

    def place_arm(self, q: np.ndarray) -> bool:
        """Set the arm at joint angles ``q`` (rad), at rest and held there (its actuators cancel gravity), without
        simulating the way there; False, and the arm left where it was, where the arm or hand would then touch
        anything but themselves."""
        d, saved = self.data, self.data.qpos[self.arm_qadr].copy()
        d.qpos[self.arm_qadr], d.qvel[self.arm_dadr] = q, 0.0
        mujoco.mj_forward(self.model, d)
        if self._robot_touches():
            d.qpos[self.arm_qadr] = saved
            mujoco.mj_forward(self.model, d)
            return False
        self.command_arm(self.gravity_feedforward())
        return True

    def _robot_touches(self) -> bool:
        """Does a geom of the arm or hand penetrate a geom that is not theirs (contacts of the last forward pass)?"""
        m, d = self.model, self.data
        root = m.body_rootid[self.model.site_bodyid[self.gripper_site]]
        robot = m.body_rootid[m.geom_bodyid] == root
        con = d.contact[:d.ncon]
        mine = robot[con.geom1] != robot[con.geom2]
        return bool(np.any(con.dist[mine] < 0.0))

    def drive_arm(self, q_target: np.ndarray, tol: float = 2e-3, timeout: float = 10.0, gain: float = 4.0,
                  control_dt: float = 0.02) -> bool:
        """Drive the arm to joint angles ``q_target`` through its actuators (P control on the joint error).

        Returns True once every joint is within ``tol`` rad and the arm has stopped, False on timeout.
        """
        steps = max(1, round(control_dt / self.model.opt.timestep))
        for _ in range(int(timeout / control_dt)):
            err = wrap_angle(np.asarray(q_target) - self.arm_q)
            if np.max(np.abs(err)) < tol and np.max(np.abs(self.data.qvel[self.arm_dadr])) < 0.02:
                return True
            self.command_arm(gain * err + self.gravity_feedforward())
            self.step(steps)
        return False


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


@functools.lru_cache(maxsize=8)
def _robot_ik(cfg: WorkcellConfig) -> ArmIK:
    robot = Workcell(cfg)
    return ArmIK(robot.model, robot.arm_qadr)


@functools.lru_cache(maxsize=8)
def _look_q(cfg: WorkcellConfig) -> np.ndarray:
    wc = Workcell(cfg)
    q, dp, dr = wc.solve_camera_ik(wc.look_camera_pose(), np.asarray(cfg.home_qpos))
    if dp > 1e-3 or dr > 1e-2:
        raise ConfigError(f"look pose unreachable: residual {dp:.4f} m, {np.rad2deg(dr):.2f} deg; "
                          "lower look_height or move the pick area closer to the arm")
    return q
