"""The hybrid hand of ``WorkcellConfig.hand = "hybrid"``: the 2-finger hand with the suction tool's cup
(``sim.suction``: the bellows on its slide joint, the stem, the rim site, the seal and hold models) between its
fingers on an actuated slide along the gripper axis, as on the MIT-Princeton gripper of the 2017 Amazon Robotics
Challenge. Retracted, the cup sits in a bore in the palm, above the fingers' contact band: the fingers pinch as the
2-finger hand does. Extended, its rim lies past the fingertips at any finger angle, so it touches a part first.

Frames: the gripper frame is the 2-finger hand's pinch site (``workcell.GRIPPER_SITE``: z along the approach, into
the part); the cup frame is the rim centre's (site ``suction.RIM_SITE``, ``suction.cup_pose``), the gripper frame
moved ``rim_offset`` along z with the bellows at rest. Lengths m, speeds m/s, times s. ``HybridConfig`` holds the
slide's settings, ``SuctionConfig`` the cup's.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from dm_control import mjcf

from posegrasp.errors import ConfigError
from posegrasp.geometry import R_to_quat, make_T
from posegrasp.sim.config import HYBRID_RETRACTED_Z, HYBRID_STEM_OVERLAP, WorkcellConfig
from posegrasp.sim.suction import PALM_BOX, PALM_Z, STEM_RADIUS, Box, ToolCylinder, add_cup, cup_height, \
    tool_cylinders

if TYPE_CHECKING:
    from posegrasp.sim.workcell import Workcell

#: Names in the hand's model (``jaco_arm/jaco_hand/...`` in a workcell): the slide's body (it carries the stem and
#: the cup's body, ``suction.CUP_BODY``), its joint (0 retracted, ``HybridConfig.extension`` extended) and actuator.
CARRIAGE_BODY, EXTEND_JOINT, EXTEND_ACTUATOR = "suction_carriage", "suction_extend", "suction_extend"
#: The contact exclusion of the palm and the cup (the bore the cup retracts into).
BORE_EXCLUDE = "suction_bore"
#: The slide's drive: an integrated-velocity actuator (its reference runs at the commanded speed between the
#: joint's ends) of stiffness (N/m) and force limit (N); the joint's damping (N s/m, about critical on the slide's
#: load) and armature (kg).
EXTEND_KP, EXTEND_FORCE, EXTEND_DAMPING, EXTEND_ARMATURE = 2000.0, 30.0, 25.0, 0.01
#: Time (s) the slide takes to settle at an end after its reference reaches it (five of its time constants).
EXTEND_SETTLE = 0.07
def _check_hand(cfg: WorkcellConfig) -> None:
    """Refuse, in one line, a workcell whose hand has no slide."""
    if cfg.hand != "hybrid":
        raise ConfigError(f"the cup's slide needs workcell hand 'hybrid', not {cfg.hand!r}")


# -- geometry -----------------------------------------------------------------------------------------------------
def rim_offset(cfg: WorkcellConfig, extended: bool = True) -> float:
    """Where the cup's rim centre lies (m, along the gripper z axis from the pinch point; the bellows at rest): 0 on
    the suction tool; on the hybrid hand ``HYBRID_RETRACTED_Z`` plus, ``extended``, the slide's stroke."""
    if cfg.hand == "suction":
        return 0.0
    _check_hand(cfg)
    return HYBRID_RETRACTED_Z + (cfg.hybrid.extension if extended else 0.0)


def T_gripper_cup(cfg: WorkcellConfig, extended: bool = True) -> np.ndarray:
    """The cup frame (rim centre, bellows at rest) in the gripper frame: ``rim_offset`` along z."""
    return make_T(np.eye(3), (0.0, 0.0, rim_offset(cfg, extended)))


def gripper_for_cup(T_world_cup: np.ndarray, cfg: WorkcellConfig) -> np.ndarray:
    """``T_world_gripper`` putting the (extended) cup's rim centre, bellows at rest, at ``T_world_cup``: the gripper
    pose of a suction pick whose cup pose a planner chose."""
    T = np.array(T_world_cup, dtype=float)
    T[:3, 3] -= rim_offset(cfg) * T[:3, 2]
    return T


def hybrid_cylinders(cfg: WorkcellConfig) -> tuple[ToolCylinder, ToolCylinder]:
    """The extended cup's stem (from the palm's face) and cup (rim at z = 0, at rest) in the cup frame, as
    ``suction.tool_cylinders`` gives the suction tool's."""
    _, cup = tool_cylinders(cfg.suction)
    return ToolCylinder(STEM_RADIUS, PALM_Z - rim_offset(cfg) - 0.003, cup.z0), cup


def hybrid_boxes(cfg: WorkcellConfig) -> list[Box]:
    """The hybrid hand in a suction pick for a clearance check (min corner, max corner; m, cup frame): the bounding
    boxes of the extended stem and cup and the palm (the fingers closed round the cup:
    ``grasping.tasks.bin_pick.planner.finger_boxes``; the hand camera: ``grasping.hand.camera_box``, each moved
    ``-rim_offset`` along z)."""
    lo, hi = np.subtract(PALM_BOX, [0.0, 0.0, rim_offset(cfg)])
    return [c.box() for c in hybrid_cylinders(cfg)] + [(tuple(lo), tuple(hi))]


# -- the model ------------------------------------------------------------------------------------------------------
def add_slide(hand: mjcf.RootElement, T_hand_gripper: np.ndarray, cfg: WorkcellConfig) -> mjcf.Element:
    """Put the cup between the 2-finger hand's fingers: on the palm, a carriage (body ``CARRIAGE_BODY``) on a slide
    joint along the gripper z axis (``EXTEND_JOINT``: range [0, extension], driven by ``EXTEND_ACTUATOR``) carries
    the suction tool's stem and cup (``suction.add_cup``), the rim at ``HYBRID_RETRACTED_Z`` retracted, inside the
    palm (whose contacts with the cup are excluded: the bore). Returns the cup's body (the welds' first body)."""
    palm, ext = hand.find("body", "hand"), cfg.hybrid.extension
    T = T_hand_gripper @ make_T(np.eye(3), (0.0, 0.0, HYBRID_RETRACTED_Z))
    carriage = palm.add("body", name=CARRIAGE_BODY, pos=T[:3, 3], quat=R_to_quat(T[:3, :3]))
    joint = carriage.add("joint", name=EXTEND_JOINT, type="slide", axis=(0, 0, 1), range=(0.0, ext),
                         limited="true", damping=EXTEND_DAMPING, armature=EXTEND_ARMATURE)
    h = cup_height(cfg.suction)
    cup = add_cup(carriage, np.eye(4), ToolCylinder(STEM_RADIUS, -h - ext - HYBRID_STEM_OVERLAP, -h), cfg.suction)
    speed = cfg.hybrid.extension_speed
    hand.actuator.add("intvelocity", name=EXTEND_ACTUATOR, joint=joint, kp=EXTEND_KP, actlimited="true",
                      actrange=(0.0, ext), ctrllimited="true", ctrlrange=(-speed, speed), forcelimited="true",
                      forcerange=(-EXTEND_FORCE, EXTEND_FORCE))
    hand.contact.add("exclude", name=BORE_EXCLUDE, body1=palm, body2=cup)
    return cup


# -- the slide ------------------------------------------------------------------------------------------------------
def extension(wc: Workcell) -> float:
    """How far (m) the cup is out: 0 retracted, ``HybridConfig.extension`` extended."""
    _check_hand(wc.cfg)
    return float(wc.data.qpos[wc.model.joint(f"jaco_arm/jaco_hand/{EXTEND_JOINT}").qposadr[0]])


def extend(wc: Workcell, out: bool = True) -> float:
    """Drive the cup out (``out``: for a suction pick) or in (for a pinch) at ``HybridConfig.extension_speed``: the
    command holds until the next one. Returns the time (s) until the cup rests at that end; a controller keeps the
    arm's control loop running meanwhile."""
    _check_hand(wc.cfg)
    a = wc.model.actuator(f"jaco_arm/jaco_hand/{EXTEND_ACTUATOR}").id
    speed, end = wc.cfg.hybrid.extension_speed, wc.cfg.hybrid.extension if out else 0.0
    wc.data.ctrl[a] = speed if out else -speed
    reference = float(wc.data.act[wc.model.actuator_actadr[a]])
    return abs(end - reference) / speed + EXTEND_SETTLE
