"""Bin picking's settings (``[bin_pick]`` of the trial settings) and its name."""

from __future__ import annotations

from dataclasses import field

from posegrasp.config import settings, within
from posegrasp.errors import ConfigError
from posegrasp.perception.held import HeldFitConfig
from posegrasp.sim.clutter import ClutterConfig
from posegrasp.sim.shaker import ShakerConfig
from posegrasp.sim.tote import ToteConfig
from posegrasp.sim.tray import TrayConfig

#: The task's name (``--task``); its records are ``record.BinPickRecord``s.
BIN_PICK = "bin-pick"

#: Where picked parts go (``--place``): dropped into the out-box, or set down in the tray's slots at their poses.
PLACES = ("out-box", "tray")
#: The tray's second look at the part held in attempt ``a`` is capture ``HELD_LOOK + a`` of its episode (its look
#: into the tote is capture ``a``).
HELD_LOOK = 1000


@settings
class BinPickConfig:
    """Bin picking: the scene, when an episode ends, and how the planner chooses, approaches and drops a part."""

    #: The scene: ``bin`` (a heap in the tote) or ``pile`` (the same heap on the table, no walls).
    scene: str = "bin"
    #: The heap: parts per episode (``parts``, at most ``max_parts``), the tote, the drop and settling.
    clutter: ClutterConfig = field(default_factory=ClutterConfig)
    #: The episode ends after this many failed attempts in a row ...
    max_failures: int = field(default=3, metadata=within(1, 1000))
    #: ... or after this many attempts per part present.
    attempts_per_part: int = field(default=2, metadata=within(1, 100))
    #: Time (s) allowed for the drive back to the look after an attempt (``control.look_timeout`` at the start).
    look_timeout: float = field(default=8.0, metadata=within(0.1, 100.0))
    #: The out-box the parts are dropped into, beside the heap (``outbox_offset``).
    outbox: ToteConfig = field(default_factory=lambda: ToteConfig(inner_size=(0.14, 0.14), wall_height=0.05))
    #: The out-box's centre this far (m, world x and y) from the heap's: beside the tote, a 34 deg turn of the arm's
    #: base away (cycle time: the place area, where it stood before, is 78 deg away).
    outbox_offset: tuple[float, float] = field(default=(0.0, 0.3), metadata=within(-2.0, 2.0))
    #: Where picked parts go (``PLACES``): ``out-box`` (dropped, any pose) or ``tray`` (set down in a slot at its pose;
    #: the tote then holds the tray's kit).
    place: str = "out-box"
    #: The tray of ``place = "tray"``, on the place area.
    tray: TrayConfig = field(default_factory=TrayConfig)
    #: Tray, second look: the shift of the part's believed pose in the hand onto the look's depth (``look_fit``).
    held_fit: HeldFitConfig = field(default_factory=HeldFitConfig)
    #: Tray: a part is placed when its model frame lies within this distance (m, xy) of its slot's ...
    pos_tol: float = field(default=0.003, metadata=within(0.0, 0.1))
    #: ... its turn about the vertical within this (deg) of the slot's, both modulo its symmetries ...
    yaw_tol_deg: float = field(default=3.0, metadata=within(0.0, 180.0))
    #: ... and its resting face within this (deg) of the face it was planned to rest on (else "wrong face up").
    face_tol_deg: float = field(default=10.0, metadata=within(0.0, 90.0))
    #: Tray: the part's bottom is let go this far (m) above the plate (the hand stops early where it touches).
    place_gap: float = field(default=0.002, metadata=within(0.0, 0.05))
    #: The hand and the carried part's bottom clear the walls' top (tote and out-box) by this much (m).
    wall_margin: float = field(default=0.02, metadata=within(0.0, 0.5))
    #: Pick order: a grasp's rank is its score plus this much per metre (1/m) its part's estimated top stands
    #: above the floor (the highest, most exposed parts first).
    height_weight: float = field(default=20.0, metadata=within(0.0, 1e4))
    #: A grasp's score loses this much per radian (1/rad) the wrist turns to it (``grasp.score.turn`` on the
    #: table): the wrist is the arm's slowest joint to turn there and back.
    turn_weight: float = field(default=1.0, metadata=within(0.0, 100.0))
    #: Parts are tried highest first; the best grasps of this many parts that have some compete.
    plan_parts: int = field(default=3, metadata=within(1, 200))
    #: A pinch whose pads lie less than this share (0-0.5: ``Grasp.support``) on the part's flat faces (a part
    #: leaning on the heap, pinched on edges or studs with the hand tilted to it) is a last resort: tried only when
    #: no part has another grasp at any of ``part_clearance``; the hybrid hand takes the cup's grasp before it.
    min_support: float = field(default=0.03, metadata=within(0.0, 0.5))
    #: The fingers open this much wider than the part they grasp (m; ``grasp.finger_margin`` on the table).
    finger_margin: float = field(default=0.01, metadata=within(0.0, 0.1))
    #: The open hand keeps this distance (m) from the other parts' estimated surfaces and the depth image's points
    #: (negative: it may push into the heap that far); from the walls it keeps ``wall_clearance``. Tried in
    #: order: the next, looser value only when no part has a grasp (or none reachable) at the one before.
    part_clearance: tuple[float, ...] = field(default=(-0.008, -0.015), metadata=within(-0.05, 0.1))
    #: The open fingers, the camera and the arm keep this far (m) from the tote's walls at a grasp (more than the
    #: arm's position tolerance, ``control.pos_tol``: it arrives a few millimetres off, a fingertip on a wall).
    wall_clearance: float = field(default=0.0065, metadata=within(0.0, 0.05))
    #: A grasp whose open fingers would touch a wall is tried again with the hand moved this far (m) along the
    #: gripper y axis (nearest first), the part sitting off-centre in the hand ...
    wall_shifts: tuple[float, ...] = (-0.024, -0.02, -0.016, -0.012, -0.008, -0.004, 0.004, 0.008, 0.012, 0.016, 0.02,
                                      0.024)
    #: ... while its contact faces still meet finger 1's pad and finger 2's or 3's this far (m) along y ...
    shift_contact: float = field(default=0.016, metadata=within(0.0, 0.05))
    #: ... and the fingers and the camera keep this far (m) from the walls (more than ``wall_clearance``:
    #: neighbours push the descending fingers sideways, and off-centre they are nearer a wall).
    shift_clearance: float = field(default=0.008, metadata=within(0.0, 0.05))
    #: A grasp that no shift clears of the walls is tried again with the hand turned about its pinch point by the
    #: least of these (deg) that clears it (about the squeeze axis or across it, its top leaning away from the wall;
    #: its score losing ``grasp.score.tilt`` per degree) ...
    wall_tilts_deg: tuple[float, ...] = (10.0, 20.0)
    #: ... raised until the open fingers keep this far (m) above the floor.
    tilt_floor_clearance: float = field(default=0.002, metadata=within(0.0, 0.05))
    #: The hybrid hand squeezes a part turned near a wall along the wall where neither its cup nor its fingers have a
    #: grasp (``bin_pick/squeeze.py``): more totes emptied, as reliable, a few picks an hour fewer.
    wall_squeeze: bool = True
    #: ... and where it has no squeeze either, rolls a round part lying on its side by a wall off it with its closed
    #: fingers (``bin_pick/roll.py``; the attempt picks nothing: "rolled off a wall").
    wall_roll: bool = True
    #: A look that finds nothing graspable (a failed attempt) is followed by a shake of the tote's stage, the parts
    #: lying against its walls sliding off them (``sim.shaker``), at most this many times an episode (0: the tote
    #: stands still on the table, on no stage; the other attempts and the heap's settling change with a stage too).
    shakes: int = field(default=0, metadata=within(0, 100))
    #: ... shaken toward the walls that the estimates' centres lie within this distance (m) of.
    shake_margin: float = field(default=0.06, metadata=within(0.0, 0.5))
    #: Also shake while the arm is away (from the lift, as it carries the part and comes back for the next look)
    #: where another estimate than the target's lies by a wall: the next look sees it off the wall. Takes from
    #: the same ``shakes``.
    shake_away: bool = False
    #: The tote's stage and its shake.
    shaker: ShakerConfig = field(default_factory=ShakerConfig)
    #: On its way down from the pre-grasp to the grasp the hand's reference waits while the hand lags it by more
    #: than this (m; elsewhere ``control.max_lag``): at the approach speed the arm sways 5-15 mm off the line where
    #: it reaches far, a fingertip or the cup on the tote's far wall (not a squeeze: its hand, tilted, is held
    #: further off the line by the posture term).
    approach_lag: float = field(default=0.004, metadata=within(0.0005, 0.1))
    #: A neighbour that stops the hand on its way down to the grasp (a guarded move): the fingers close where the hand
    #: stopped if its pinch point stands at most this far (m) above the grasp ...
    close_slack: float = field(default=0.025, metadata=within(0.0, 0.1))
    #: ... and this far (m) beside it; else the attempt fails ("collision").
    close_slack_side: float = field(default=0.012, metadata=within(0.0, 0.1))
    #: A protective stop: a pick ends ("collision") when contacts turn the hand this far (deg) from the grasp's
    #: approach (a fingertip caught on the floor or a part while the arm pushes on: the hand pivots about it).
    tilt_stop_deg: float = field(default=15.0, metadata=within(1.0, 90.0))
    #: A grasp that failed is not tried again: no grasp within this distance (m) of its pose ...
    retry_distance: float = field(default=0.01, metadata=within(0.0, 1.0))
    #: ... and this angle (deg) of its squeeze axis.
    retry_angle_deg: float = field(default=20.0, metadata=within(0.0, 180.0))
    #: One depth pixel in this many, along each image axis, becomes an obstacle point of the grasp planner.
    depth_stride: int = field(default=4, metadata=within(1, 64))
    #: Depth points within this distance (m) of the target's estimated surface are the target, not obstacles.
    own_margin: float = field(default=0.008, metadata=within(0.0, 0.1))
    #: Depth points lower than this (m) above the floor are the floor; the robot believes the tote empty when it
    #: sees no part and no depth point higher.
    floor_band: float = field(default=0.006, metadata=within(0.0, 0.1))
    #: Depth points within this distance (m) of the tote's walls are the walls.
    wall_band: float = field(default=0.008, metadata=within(0.0, 0.1))
    #: Another part counts as lifted with the target when it rose this far (m).
    double_rise: float = field(default=0.03, metadata=within(0.001, 1.0))
    #: Suction: the cup comes down along a face's inward normal lying within this angle (deg) of straight down.
    suction_max_tilt_deg: float = field(default=40.0, metadata=within(0.0, 80.0))
    #: Suction: points drawn on each part type's surface where the cup may seal (with its flat faces' centres).
    suction_samples: int = field(default=400, metadata=within(1, 100000))
    #: Suction: the cup and the wrist keep this far (m) from the other parts' estimated surfaces and depth points.
    suction_clearance: float = field(default=0.002, metadata=within(0.0, 0.1))
    #: Suction: the cup and the wrist keep this far (m) from the tote's walls.
    suction_wall_clearance: float = field(default=0.005, metadata=within(0.0, 0.1))
    #: Suction: a spot is taken only where the cup seals slid this far (m) any way (``edge_margin``: 0, 2, 4 or
    #: 6 mm): the arm sets the cup down a millimetre or two off its target.
    suction_min_edge_margin: float = field(default=0.002, metadata=within(0.0, 0.006))
    #: Suction: the depth image's points under the cup's rim must lie within this distance (m) of the face it is
    #: planned on, none rising into the cup (``suction_grasps.seen_seals``; 0: the estimate's model alone decides).
    suction_seen_tol: float = field(default=0.003, metadata=within(0.0, 0.05))
    #: Suction score: plus this per metre (1/m) of seal margin and of edge margin (how far the cup may slide off).
    suction_margin_weight: float = field(default=100.0, metadata=within(0.0, 1e4))
    #: Suction score: minus this per metre (1/m) from the part's centre of mass to the cup's axis (moment arm).
    suction_com_weight: float = field(default=40.0, metadata=within(0.0, 1e4))
    #: Suction score: minus this per degree (1/deg) of the approach's tilt from straight down.
    suction_tilt_weight: float = field(default=0.01, metadata=within(0.0, 100.0))

    def __post_init__(self) -> None:
        if self.place not in PLACES:
            raise ConfigError(f"bin_pick.place {self.place!r} is not a place; choose one of: {', '.join(PLACES)}")
        if not self.part_clearance:
            raise ConfigError("bin_pick.part_clearance must be one or more distances (m) in [-0.05, 0.1], got []")
        if not all(0.0 < t <= 40.0 for t in self.wall_tilts_deg):
            raise ConfigError(f"bin_pick.wall_tilts_deg must be angles (deg) in (0, 40], got "
                              f"{list(self.wall_tilts_deg)}")
        if self.shake_away and not self.shakes:
            raise ConfigError("bin_pick.shake_away shakes from the episode's shakes, and shakes = 0 gives it none; "
                              "set shakes = N (N >= 1)")
        if self.shakes and self.scene == "pile":
            raise ConfigError(f"bin_pick.shakes = {self.shakes} shakes the tote, and a pile has none; use --scene bin "
                              "or shakes = 0")
