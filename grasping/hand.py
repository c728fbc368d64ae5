"""The Jaco hand as the grasp planner models it: where a block sits in the hand, the finger pads, and the open
hand's boxes for the clearance check, from the jaco_hand meshes; the 3-finger hand (``KG3``) and the 2-finger
one (``KG2``, ``WorkcellConfig.hand``).

Lengths in metres, in the gripper frame of the pinch site (``grasping.grasps``): origin at the pinch point,
z the approach direction (down into the block), x the squeeze axis (finger 1 on +x, the fingers facing it on -x:
2 and 3, or 3 alone).
"""

from __future__ import annotations

from dataclasses import dataclass

Box = tuple[tuple[float, float, float], tuple[float, float, float]]

#: Half width (m) of a finger pad along the gripper y axis: the pads squeeze the block's surface within it.
PAD_HALF_WIDTH = 0.012
#: Heights (m, along z: negative above) relative to the pinch point that the closing fingertips touch.
CONTACT_BAND = (-0.008, 0.012)
#: A surface point within this distance (m) of a plane lies on it: of a contact face (the block's extreme
#: plane along the squeeze axis), or of a height the contact face must reach (``FACE_REACH``).
ON_PLANE_TOL = 0.0015
#: Fingertips reach this far (m) past the pinch point along z (they curl past it when closing).
TIP_BELOW = 0.012
#: A part whose top lies below the lowest pinch height (``GraspConfig.min_pinch_height``) is pinched this much
#: lower (m): the curling fingertips then brush the table without catching on it, and grip a flat part's edges
#: (a 6.4 mm domino lying flat) with more than their very ends. Lower, they strike the table.
FLAT_PINCH_DROP = 0.004
#: Thickness (m) of a finger, outward along x from its pad (at half the opening).
FINGER_THICKNESS = 0.03
#: The palm: an axis-aligned box (m, (min corner, max corner)) starting 7 cm above the pinch point.
PALM = ((-0.06, -0.065, -1.0), (0.06, 0.035, -0.07))
#: A yaw-stable pinch's contact face reaches this far (m) past the inner pad edges of fingers 2 and 3 ...
PAD_OVERLAP = 0.004
#: ... within this height (m) of the pinch point ...
PAD_FACE_HEIGHT = 0.004
#: ... and this far (m) above and below the pinch point, where the fingertips press.
FACE_REACH = 0.003


@dataclass(frozen=True)
class Hand:
    """A hand's layout along the gripper y axis (m): ``hand_y``, where the grasped block's centre sits;
    ``finger1_y`` and ``facing_y``, the extents of finger 1 and of each finger facing it (boxes round the open
    fingers' meshes); ``all_axes``: it may squeeze a block along any of its axes, across a brick's studs and a
    lying cylinder's end discs too (``grasps.squeeze_axes``)."""

    hand_y: float
    finger1_y: tuple[tuple[float, float], ...]
    facing_y: tuple[tuple[float, float], ...]
    all_axes: bool = False

    @property
    def paired(self) -> bool:
        """Do two fingers face finger 1 (finger 1 against one of them alone turns the block in the hand)?"""
        return len(self.facing_y) == 2

    def boxes(self, o: float) -> list[Box]:
        """The open hand as axis-aligned boxes (min corner, max corner; m, gripper frame): finger 1, the fingers
        facing it, their pads ``o`` m either side of the pinch point along x (half the opening), each from
        ``TIP_BELOW`` past the pinch point up out of reach, and the palm."""
        return ([((o, y0, -1.0), (o + FINGER_THICKNESS, y1, TIP_BELOW)) for y0, y1 in self.finger1_y]
                + [((-o - FINGER_THICKNESS, y0, -1.0), (-o, y1, TIP_BELOW)) for y0, y1 in self.facing_y] + [PALM])


#: The 3-finger hand: the block sits between finger 1 and finger 3.
KG3 = Hand(hand_y=-0.005, finger1_y=((-0.032, 0.002),), facing_y=((-0.062, -0.022), (-0.002, 0.032)))
#: The 2-finger hand: finger 1 and finger 3 facing it, both centred on the pinch point (their meshes reach 11.5 mm
#: either side); its pads also hold a brick across its studs and a lying cylinder by its end discs.
KG2 = Hand(hand_y=0.0, finger1_y=((-0.012, 0.012),), facing_y=((-0.012, 0.012),), all_axes=True)


def hand_of(cfg) -> Hand:
    """The planner's model of the hand of a workcell (``WorkcellConfig.hand``)."""
    return KG2 if cfg.hand in ("2-finger", "hybrid") else KG3


#: Half width (m) of the hand camera's housing along the gripper x axis and y axis (``camera_box``).
CAMERA_HALF = (0.025, 0.02)


def camera_box(mount_pos: tuple[float, float, float]) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """The hand camera and its housing as an axis-aligned box (min corner, max corner; m, gripper frame) around
    its mount ``mount_pos`` (``CameraConfig.mount_pos``), from 2 cm below the mount up out of reach, like the
    palm: obstacles under it (a tote's wall) would hit the camera before the fingers reach the grasp."""
    x, y, z = mount_pos
    return (x - CAMERA_HALF[0], y - CAMERA_HALF[1], -1.0), (x + CAMERA_HALF[0], y + CAMERA_HALF[1], z + 0.02)
