"""Typed settings of the grasp trials: control, grasp planning, scoring and scenes.

Lengths in metres, times in seconds (simulated unless the name says ``wall``), angles in degrees where
the name says ``_deg``. Any field can be set from a TOML file of the same layout (``--config``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from posegrasp import ASSETS
from posegrasp.grasping.support import RestConfig
from posegrasp.config import load_toml, within
from posegrasp.sim.scene import SceneConfig

#: The shipped hand-eye calibration (``posegrasp calibrate``), used by the trials.
HAND_EYE_JSON = ASSETS / "calibration" / "hand_eye.json"


@dataclass(frozen=True)
class ControlConfig:
    """Closed-loop differential IK (mink) driving the arm's velocity actuators."""

    #: Control period (s): one IK solve per period, physics steps in between.
    dt: float = 0.04
    #: Peak Cartesian speed of the gripper along a straight segment (m/s).
    speed: float = 0.4
    #: Peak rotation speed of the gripper (rad/s).
    angular_speed: float = 2.0
    #: A segment is reached within this position error (m) and `rot_tol_deg`.
    pos_tol: float = 0.004
    #: A segment is reached within this orientation error (deg) and `pos_tol`.
    rot_tol_deg: float = 3.0
    #: The reference waits while the hand lags it by more than this (m) or `max_lag_deg`.
    max_lag: float = 0.02
    #: The reference waits while the hand lags it by more than this angle (deg).
    max_lag_deg: float = 10.0
    #: Time (s) allowed after a segment's nominal duration to reach it.
    settle_timeout: float = 1.5
    #: Fraction of the pose error the IK removes per control period.
    frame_gain: float = 0.8
    #: Orientation weight of the IK's gripper task (position weight 1).
    orientation_cost: float = 0.5
    #: Weight of the IK's pull toward the look pose's joint angles.
    posture_cost: float = 0.01
    #: Hand and arm keep this distance (m) from the table.
    table_clearance: float = 0.002
    #: Finger closing velocity command (rad/s).
    finger_speed: float = 4.0
    #: Finger opening speed when releasing a block (rad/s).
    release_speed: float = 0.6
    #: Any joint faster than this (rad/s or m/s) is a simulation error.
    max_speed: float = 50.0
    #: The arm has reached the look pose when every joint is within this (rad).
    look_tol: float = 0.01
    #: Time (s) allowed to reach the look pose, else the episode times out.
    look_timeout: float = 4.0
    #: P gain (1/s) of the joint drive to the look pose.
    look_gain: float = 10.0


@dataclass(frozen=True)
class GraspConfig:
    """Grasp candidates, their filters and scores; the place and scoring rules."""

    max_width: float = 0.085  # widest graspable span across the fingers (m)
    min_width: float = 0.012  # narrowest
    contact_depths: tuple[float, ...] = (0.010, 0.018, 0.026, 0.034)  # pinch point this far below the block's
    # top (m): the one with the flattest contact faces nearest the block centre's height ...
    min_pinch_height: float = 0.014  # ... but at least this high above the table (fingertips clear it)
    max_tilt_deg: float = 50.0  # candidate approach directions within this angle of straight down
    clearance_min: float = 0.004  # neighbours' surfaces at least this far from the finger box (m)
    reach_tol: float = 0.004  # IK position residual (m) accepted as reachable
    grasps_per_block: int = 4  # the best this many grasps of each estimated block compete ...
    detection_weight: float = 0.2  # ... ranked by grasp score + this x the estimate's confidence ...
    ik_checks: int = 8  # ... and the best this many are checked for reachability, in rank order
    neighbour_points: int = 300  # surface points per neighbouring estimate for the clearance check
    pregrasp_height: float = 0.08  # approach starts this far above the grasp (m)
    finger_margin: float = 0.03  # the fingers pre-shape, and open on release, this much wider than the grasp (m)
    approach_speed: float = 0.25  # peak speed of the approach and of the place descent (m/s)
    carry_speed: float = 0.5  # peak speed while carrying (m/s; the joint speed limits usually bind first)
    release_time: float = 0.6  # the fingers open for at most this long before the retreat (s)
    release_push: float = 0.008  # while opening, the hand pushes this far down (m)
    lift_height: float = 0.10  # the block's bottom is lifted to this height (m)
    place_gap: float = 0.004  # the block is brought this far above the place pad (m), then lowered ...
    place_press: float = 0.003  # ... until it touches, at most this far into the pad (m), and released
    place_descent_speed: float = 0.03  # peak speed of that last descent until the block touches (m/s)
    place_approach: float = 0.03  # the carry ends this far above the place pose; the last part is slow (m)
    retreat_height: float = 0.055  # after releasing, the fingertips rise this far above the block's top (m)
    fingertip_depth: float = 0.012  # the fingertips reach this far below the pinch point (m)
    place_jitter: float = 0.02  # random offset of the place target from the pad centre (m)
    # The kitting and stack tasks, where the block's yaw in the hand matters, pinch yaw-stably: the block's
    # centre near this far along the gripper y axis (m; pick-and-place: grasps.HAND_Y, -5 mm), between the
    # pads of fingers 2 and 3 (grasps.plan_grasps), and the fingers close up to this many control periods
    # more until all three touch.
    pose_hand_y: float = -0.012
    pose_finger_wait: int = 10
    # The stack task also lets the arm stop swaying (5-8 mm after a fast descent) before closing and before
    # setting the block down: the gripper moving slower than pose_settle_speed (m/s) for 3 control periods in a
    # row, at most pose_settle_time (s) (the controller keeps a steady offset of 1-1.5 mm from its target, so
    # a distance to the target does not tell a still arm); and sets the block down from pose_place_gap (m)
    # above its surface (guarded, slowly), so a block that slid down in the fingers touches the base slowly too.
    # Kitting does not: an L-block turns in the hand while held (7-10 deg), and the longer hold took it past 10 deg.
    pose_settle_speed: float = 0.005
    pose_settle_time: float = 1.0
    pose_place_gap: float = 0.02
    pose_approach_speed: float = 0.1  # stack: the approach and place descent (m/s; approach_speed sways the arm)


@dataclass(frozen=True)
class ScoringConfig:
    """Success criteria and the failure taxonomy thresholds."""

    #: Grasp success: the block's bottom at least this high (m) for `hold_time`.
    lift_min: float = 0.05
    #: Grasp success: the block held up for this long (s).
    hold_time: float = 1.0
    #: Place success: the block within this xy distance (m) of its target, released and at rest.
    place_tol: float = 0.025
    #: Place success: the hand at least this far (m) from the block.
    hand_away: float = 0.05
    #: The block is at rest below these speeds (m/s, rad/s).
    rest_speed: tuple[float, float] = (0.01, 0.2)
    #: The block is at rest after this many control periods in a row below `rest_speed`.
    rest_periods: int = 3
    #: Time (s) allowed for the block to come to rest after release.
    rest_timeout: float = 1.5
    #: A failed episode counts as "pose error" when the target's ADD(-S) exceeds this x its diameter.
    pose_error_frac: float = 0.1
    #: Surface points of the block model for ADD and ADD-S.
    pose_error_points: int = 500
    #: Oracle: blocks with fewer visible mask pixels (at 640x480) are not detected.
    min_visible_px: int = 150


@dataclass(frozen=True)
class KittingConfig:
    """The kitting task (``grasping.tasks``): the block must end upright on the pad at the kit's yaw."""

    pos_tol: float = 0.015  # success: its centre within this xy distance of the kit's (m) ...
    yaw_tol_deg: float = 10.0  # ... its yaw within this of the kit's, both modulo its symmetries ...
    upright_tol_deg: float = 15.0  # ... and its upright face within this of straight down ("wrong face up")
    belief_tol_deg: float = 20.0  # the planner targets only estimates this close to upright
    kit_yaw_deg: float = 0.0  # the kit's yaw on the pad (world, deg)


@dataclass(frozen=True)
class StackConfig:
    """The stack task (``grasping.tasks``): a block set centred on a base block standing on the pad."""

    pos_tol: float = 0.01  # success: its centre within this xy distance of the base's top centre (m) ...
    yaw_tol_deg: float = 10.0  # ... its yaw within this of the base's, modulo both blocks' symmetries ...
    upright_tol_deg: float = 15.0  # ... upright ...
    rest_time: float = 1.0  # ... resting there this long after the hand has left (s) ...
    base_move_tol: float = 0.005  # ... and the base moved at most this far (m)
    belief_tol_deg: float = 20.0  # the planner targets only estimates this close to upright
    base_jitter: float = 0.02  # the base's centre is drawn this far (m, per axis) around the pad centre
    look_height: float = 0.3  # the hand camera looks down at the pad from this height (m)


#: The trial tasks (``--task``): ``grasping.tasks``.
TASKS = ("pick-place", "kitting", "stack")


@dataclass(frozen=True)
class TrialConfig:
    """One trial campaign: scenes of ``min_blocks``-``max_blocks`` blocks, control, grasps, scoring."""

    #: Fewest blocks in a scene.
    min_blocks: int = 1
    #: Most blocks in a scene.
    max_blocks: int = 5
    #: Hand-eye calibration file (`T_gripper_cam`) the planner uses (`posegrasp calibrate` writes one).
    hand_eye: str = str(HAND_EYE_JSON)
    #: Elliptic friction cones, so that grasped blocks do not creep out of the fingers.
    elliptic_cones: bool = True
    #: MuJoCo impedance ratio of the contacts (high: less creep in the fingers).
    impratio: float = 10.0
    #: Tasks that hold the block firmly (yaw-stable pinch, noslip, sleep); unset: the set's, else kitting and stack.
    firm_hold_tasks: tuple[str, ...] | None = None
    #: Firm hold: MuJoCo noslip solver iterations per physics step, which stop slow slip in the fingers; 0: off.
    pose_noslip_iterations: int = field(default=2, metadata=within(0, 1000))
    #: Firm hold: MuJoCo sleeping islands, bodies at rest not simulated until something touches them.
    pose_sleep: bool = True
    #: Firm hold: speed below which a body may sleep (MuJoCo's sleep tolerance).
    pose_sleep_tolerance: float = field(default=1e-3, metadata=within(0.0, 1.0))
    #: MuJoCo solref time constant (s) of the table's and pad's contacts after settling (0.02 lets bricks walk).
    support_timeconst: float = 0.01
    #: Arm control.
    control: ControlConfig = field(default_factory=ControlConfig)
    #: Grasp planning and motions.
    grasp: GraspConfig = field(default_factory=GraspConfig)
    #: Success criteria and failure reasons.
    scoring: ScoringConfig = field(default_factory=ScoringConfig)
    #: Levelling of pose estimates onto the table (`grasping/support.py`).
    rest: RestConfig = field(default_factory=RestConfig)
    #: Scene randomisation and the workcell.
    scene: SceneConfig = field(default_factory=lambda: SceneConfig(settle_timeout=2.0))
    #: The task: `pick-place`, `kitting` or `stack` (`--task`).
    task: str = "pick-place"
    #: The kitting task.
    kitting: KittingConfig = field(default_factory=KittingConfig)
    #: The stack task.
    stack: StackConfig = field(default_factory=StackConfig)
    #: Wall seconds a provider may take per capture before the episode fails as "perception error"; 0: no limit.
    perception_timeout_s: float = field(default=60.0, metadata=within(0.0, 86400.0))


#: The tasks that hold firmly where neither the campaign nor its object set says.
DEFAULT_FIRM_HOLD_TASKS = ("kitting", "stack")


def firm_hold_tasks(cfg: TrialConfig) -> tuple[str, ...]:
    """The tasks that hold the block firmly: ``cfg.firm_hold_tasks``, else the object set's, else the default."""
    if cfg.firm_hold_tasks is not None:
        return cfg.firm_hold_tasks
    from posegrasp.catalog import set_firm_hold_tasks

    tasks = set_firm_hold_tasks(cfg.scene.workcell.objects)
    return DEFAULT_FIRM_HOLD_TASKS if tasks is None else tasks


def firm_hold(cfg: TrialConfig) -> bool:
    """Does the campaign's task hold the block firmly (``firm_hold_tasks``)?"""
    return cfg.task in firm_hold_tasks(cfg)


def load_trial_config(path: str | Path | None = None) -> TrialConfig:
    """Trial settings from a TOML file, or the defaults."""
    return load_toml(TrialConfig, path)


def with_set(cfg: TrialConfig, objects: str | Path | None = None) -> TrialConfig:
    """``cfg`` on the object set ``objects`` (None: the one ``cfg`` names; ``""``: the shipped blocks), its folder
    made absolute and checked (``sim.config.with_objects``), and its firm-hold tasks settled (``firm_hold_tasks``,
    so the campaign records them)."""
    from posegrasp.sim.config import with_objects

    cfg = dataclasses.replace(cfg, scene=dataclasses.replace(cfg.scene, workcell=with_objects(cfg.scene.workcell,
                                                                                               objects)))
    return dataclasses.replace(cfg, firm_hold_tasks=firm_hold_tasks(cfg))
