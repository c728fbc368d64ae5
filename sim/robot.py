"""The robot of the workcell: dm-control's Jaco2 arm (``JacoArm``, with its velocity actuators) and a hand
(``WorkcellConfig.hand``: dm-control's 3-finger ``JacoHand``, the 2-finger hand made from it, the suction tool of
``sim.suction`` or the hybrid hand of ``sim.hybrid``), the hand camera on its mount. ``robot_mjcf`` composes it with
``dm_control.mjcf``; ``robot_spec`` keeps it parsed, once per process, for ``sim.workcell.compile_workcell`` to
attach to each workcell's world at ``ROBOT_MOUNT``, its names prefixed ``ROBOT_PREFIX``."""

from __future__ import annotations

import mujoco
import numpy as np
from dm_control import mjcf
from dm_control.entities.manipulators.kinova import JacoArm, JacoHand

from posegrasp.errors import ConfigError
from posegrasp.geometry import R_to_quat, invert, make_T, quat_to_R
from posegrasp.sim.camera import add_mjcf_camera, rpy_deg_to_R
from posegrasp.sim.config import HANDS, WorkcellConfig
from posegrasp.sim.hybrid import add_slide
from posegrasp.sim.suction import add_tool

HAND_CAMERA = "hand_camera"
GRIPPER_SITE = "pinchsite"
#: The world's body that carries the robot, and the prefix of the robot's names in the workcell.
ROBOT_MOUNT, ROBOT_PREFIX = "jaco_arm", "jaco_arm/"


def _element_T(elem) -> np.ndarray:
    """Pose of an MJCF element in its parent body from its ``pos`` and ``quat`` (identity when unset)."""
    pos = np.zeros(3) if elem.pos is None else np.asarray(elem.pos, dtype=float)
    quat = np.array([1.0, 0, 0, 0]) if elem.quat is None else np.asarray(elem.quat, dtype=float)
    return make_T(quat_to_R(quat), pos)


def robot_mjcf(cfg: WorkcellConfig) -> tuple[mjcf.RootElement, str | None]:
    """Compose the robot: dm-control's Jaco2 arm with ``cfg.hand`` (the 3-finger hand, the 2-finger one made from
    it, the suction tool or the hybrid hand), the hand camera and its housing. Returns the arm's root and the cup's
    body name in the workcell (None without a cup)."""
    if cfg.hand not in HANDS:
        raise ConfigError(f"workcell hand {cfg.hand!r} is not a hand; choose one of: {', '.join(HANDS)}")
    arm, hand = JacoArm(), JacoHand()
    hand_body = hand.mjcf_model.find("body", "hand")
    T_hand_gripper = _element_T(hand.mjcf_model.find("site", GRIPPER_SITE))
    c = cfg.hand_camera
    T_gripper_cam = make_T(rpy_deg_to_R(c.mount_rpy_deg), c.mount_pos)
    add_mjcf_camera(hand_body, HAND_CAMERA, T_hand_gripper @ T_gripper_cam, c)
    T_hand_cam = T_hand_gripper @ T_gripper_cam
    hand_body.add("geom", name="camera_housing", type="box", size=(0.02, 0.011, 0.012),
                  pos=T_hand_cam[:3, 3] - 0.014 * T_hand_cam[:3, 2], quat=R_to_quat(T_hand_cam[:3, :3]),
                  rgba=(0.12, 0.12, 0.14, 1), mass=0.05, contype=2, conaffinity=0, group=1)
    cup = None
    if cfg.hand in ("2-finger", "hybrid"):
        _two_fingers(hand.mjcf_model, T_hand_gripper)
    if cfg.hand == "hybrid":
        cup = add_slide(hand.mjcf_model, T_hand_gripper, cfg)
    elif cfg.hand == "suction":
        cup = add_tool(hand.mjcf_model, T_hand_gripper, cfg.suction)
    arm.attach(hand)
    return arm.mjcf_model, None if cup is None else f"{ROBOT_PREFIX}{hand.mjcf_model.model}/{cup.name}"


#: ``robot_spec``'s parsed robots, by the settings they depend on.
_ROBOTS: dict[tuple, tuple[mujoco.MjSpec, dict, str | None]] = {}


def robot_spec(cfg: WorkcellConfig) -> tuple[mujoco.MjSpec, dict, str | None]:
    """``robot_mjcf`` parsed once per robot (hand, camera mount, cup and slide): its spec (shared: attach a copy),
    its mesh files and the cup's body name."""
    key = (cfg.hand, cfg.hand_camera, cfg.suction, cfg.hybrid)
    if key not in _ROBOTS:
        root, cup = robot_mjcf(cfg)
        assets = root.get_assets()
        _ROBOTS[key] = mujoco.MjSpec.from_string(root.to_xml_string(), assets), assets, cup
    return _ROBOTS[key]


def _two_fingers(hand: mjcf.RootElement, T_hand_gripper: np.ndarray) -> None:
    """Make dm-control's 3-finger hand the 2-finger one: finger 2 (its body, actuator and contact exclusion) goes;
    finger 1 turns about its knuckle until its hinge axis is the gripper's -y (unsplayed: the 3-finger hand's hinges
    lean 11-12 deg off the y axis) and moves onto the gripper's xz plane, and finger 3 becomes its copy turned half
    a turn about the gripper z axis through the pinch point: two 23 mm wide fingers facing each other across the
    squeeze axis x, centred on the pinch point."""
    f2 = hand.find("body", "b_finger_2")
    for ex in hand.contact.exclude:
        if ex.body2 is f2:
            ex.remove()
    hand.find("actuator", "finger_2").remove()
    f2.remove()
    f1, f3 = hand.find("body", "b_finger_1"), hand.find("body", "b_finger_3")
    G = invert(T_hand_gripper) @ _element_T(f1)  # finger 1 in the gripper frame; its hinge axis is its z
    v, c = np.cross(G[:3, 2], (0.0, -1.0, 0.0)), -float(G[1, 2])  # the least turn taking the hinge onto -y:
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])  # I + [v]x + [v]x^2 / (1 + c)
    G[:3, :3] = (np.eye(3) + K + K @ K / (1.0 + c)) @ G[:3, :3]
    G[1, 3] = 0.0
    T1 = T_hand_gripper @ G
    half_turn = T_hand_gripper @ make_T(np.diag([-1.0, -1.0, 1.0]), np.zeros(3)) @ invert(T_hand_gripper)
    for body, T in ((f1, T1), (f3, half_turn @ T1)):
        body.pos, body.quat = T[:3, 3], R_to_quat(T[:3, :3])
