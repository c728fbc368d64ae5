"""Typed settings of the grasp trials: control, grasp planning, scoring, firm holds and scenes; each task's own
settings are in its module (``grasping.tasks.kitting.KittingConfig``, ``grasping.tasks.stack.StackConfig``,
``grasping.tasks.bin_pick.BinPickConfig``).

Lengths in metres, times in seconds (simulated unless the name says ``wall``), angles in degrees where
the name says ``_deg``. Any field can be set from a TOML file of the same layout (``--config``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import field
from pathlib import Path

from posegrasp import ASSETS
from posegrasp.config import load_toml, settings, within
from posegrasp.grasping.hand import TIP_BELOW
from posegrasp.grasping.support import RestConfig
from posegrasp.grasping.tasks.bin_pick.config import BinPickConfig
from posegrasp.grasping.tasks.kitting import KittingConfig
from posegrasp.grasping.tasks.stack import StackConfig
from posegrasp.sim.config import workcell_record
from posegrasp.sim.scene import SceneConfig

#: The tasks that hold the block firmly unless the campaign (``firm_hold_tasks``) or its object set says otherwise.
FIRM_HOLD_TASKS = ("kitting", "stack", "bin-pick")
#: The shipped hand-eye calibration (``posegrasp calibrate``), used by the trials.
HAND_EYE_JSON = ASSETS / "calibration" / "hand_eye.json"


@settings
class ControlConfig:
    """Closed-loop differential IK (mink) driving the arm's velocity actuators."""

    #: Control period (s): one IK solve per period, physics steps in between.
    dt: float = field(default=0.04, metadata=within(0.0001, 1.0))
    #: Peak Cartesian speed of the gripper along a straight segment (m/s).
    speed: float = field(default=0.4, metadata=within(0.001, 10))
    #: Peak rotation speed of the gripper (rad/s).
    angular_speed: float = field(default=2.0, metadata=within(0.001, 100))
    #: A segment is reached within this position error (m) and `rot_tol_deg`.
    pos_tol: float = field(default=0.004, metadata=within(1e-06, 0.5))
    #: A segment is reached within this orientation error (deg) and `pos_tol`.
    rot_tol_deg: float = field(default=3.0, metadata=within(0.001, 180))
    #: The reference waits while the hand lags it by more than this (m) or `max_lag_deg`.
    max_lag: float = field(default=0.02, metadata=within(0.0001, 1))
    #: The reference waits while the hand lags it by more than this angle (deg).
    max_lag_deg: float = field(default=10.0, metadata=within(0.1, 180))
    #: Time (s) allowed after a segment's nominal duration to reach it.
    settle_timeout: float = field(default=1.5, metadata=within(0, 100))
    #: Fraction of the pose error the IK removes per control period.
    frame_gain: float = field(default=0.8, metadata=within(0.001, 1))
    #: Orientation weight of the IK's gripper task (position weight 1).
    orientation_cost: float = field(default=0.5, metadata=within(0, 1000.0))
    #: Weight of the IK's pull toward the look pose's joint angles.
    posture_cost: float = field(default=0.01, metadata=within(0, 1000.0))
    #: Hand and arm keep this distance (m) from the table.
    table_clearance: float = field(default=0.002, metadata=within(0, 0.1))
    #: Finger closing velocity command (rad/s).
    finger_speed: float = field(default=4.0, metadata=within(0.001, 100))
    #: Finger opening speed when releasing a block (rad/s).
    release_speed: float = field(default=0.6, metadata=within(0.001, 100))
    #: Any joint faster than this (rad/s or m/s) is a simulation error.
    max_speed: float = field(default=50.0, metadata=within(0.001, 10000.0))
    #: The arm has reached the look pose when every joint is within this (rad).
    look_tol: float = field(default=0.01, metadata=within(1e-06, 1))
    #: Time (s) allowed to reach the look pose, else the episode times out.
    look_timeout: float = field(default=4.0, metadata=within(0.01, 1000))
    #: P gain (1/s) of the joint drive to the look pose.
    look_gain: float = field(default=10.0, metadata=within(0.001, 10000.0))


@settings
class GraspScoreConfig:
    """Weights of the grasp score that ranks a block's feasible grasps (higher is better)::

        score = support * s - tilt * tilt_deg - off_centre * d - turn * yaw_turn - width * w
                + clearance * min(c, clearance_cap) [- unopposed]

    ``s``: the share of the contact window on the two contact planes (0-0.5), ``d``: the pinch point's
    horizontal distance (m) from the block's centre, ``w``: the span (m) across the fingers, ``c``: the open
    hand's clearance (m) from the neighbours' surfaces (``grasping.grasps.plan_grasps``)."""

    #: Reward per unit of flat-contact share (0-0.5): fingers on flat faces, not studs or curves.
    support: float = 2.0
    #: Penalty per degree (1/deg) the approach leans from straight down.
    tilt: float = 0.01
    #: Penalty per metre (1/m) the pinch point lies off the block's centre, horizontally (less torque).
    off_centre: float = 30.0
    #: Penalty per radian (1/rad) the wrist turns from its current yaw.
    turn: float = 0.3
    #: Penalty per metre (1/m) of span across the fingers.
    width: float = 2.0
    #: Reward per metre (1/m) of the open hand's clearance from the neighbours, up to ``clearance_cap``.
    clearance: float = 20.0
    #: Clearance (m) beyond which more earns nothing.
    clearance_cap: float = 0.02
    #: Score taken off a block's grasps that are not yaw-stable when some are (the tasks that hold firmly).
    unstable: float = 1.0
    #: Score taken off a grasp whose contact faces do not oppose within twice the friction cone (a prism pinched on
    #: its slopes slips out of two in five): a last resort, for a part with no other grasp (a prism's end caps
    #: against a wall).
    unopposed: float = 2.0
    #: Pinch height choice: flat-contact share less this per metre (1/m) of distance from the block centre's height.
    pinch_height: float = 5.0


@settings
class GraspConfig:
    """Grasp candidates, their filters and scores; the place and scoring rules."""

    #: Widest graspable span across the fingers (m).
    max_width: float = 0.085
    #: Narrowest graspable span across the fingers (m).
    min_width: float = 0.012
    #: Pinch heights tried below the block's top (m); the flattest contact nearest the centre's height wins
    #: (``score.pinch_height``).
    contact_depths: tuple[float, ...] = (0.010, 0.018, 0.026, 0.034)
    #: Lowest pinch height above the table (m), so the fingertips clear it.
    min_pinch_height: float = 0.014
    #: Approach directions within this angle of straight down are candidates (deg).
    max_tilt_deg: float = 50.0
    #: Neighbours' estimated surfaces keep at least this distance from the open hand (m).
    clearance_min: float = 0.004
    #: IK position residual accepted as reachable (m).
    reach_tol: float = 0.004
    #: The best this many grasps of each estimated block compete for the pick.
    grasps_per_block: int = field(default=4, metadata=within(1, 1000))
    #: Those grasps are ranked by grasp score plus this times the estimate's confidence.
    detection_weight: float = 0.2
    #: The best this many ranked grasps are checked for reachability, in rank order.
    ik_checks: int = field(default=8, metadata=within(1, 1000))
    #: Surface points sampled per neighbouring estimate for the clearance check.
    neighbour_points: int = field(default=300, metadata=within(1, 100000))
    #: Height of the pre-grasp pose above the grasp, where the approach starts (m).
    pregrasp_height: float = 0.08
    #: Pre-shape and release opening beyond the grasp width (m); the clearance check models it.
    finger_margin: float = 0.03
    #: Peak speed of the approach and of the place descent (m/s).
    approach_speed: float = 0.25
    #: Peak speed while carrying (m/s; the joint speed limits usually bind first).
    carry_speed: float = 0.5
    #: The fingers open for at most this long before the retreat (s).
    release_time: float = 0.6
    #: While the fingers open, the hand pushes this far down (m).
    release_push: float = 0.008
    #: The block's bottom is lifted to this height (m).
    lift_height: float = 0.10
    #: The carried block is brought this far above the place pad (m), then lowered until it touches.
    place_gap: float = 0.004
    #: The last descent goes at most this far into the pad (m) before the release.
    place_press: float = 0.003
    #: Peak speed of the last descent until the block touches (m/s).
    place_descent_speed: float = 0.03
    #: The carry ends this far above the place pose; the last part is slow (m).
    place_approach: float = 0.03
    #: After the release, the fingertips rise this far above the block's top (m).
    retreat_height: float = 0.055
    #: The fingertips reach this far below the pinch point (m; the hand's ``grasping.hand.TIP_BELOW``).
    fingertip_depth: float = TIP_BELOW
    #: Random offset of the place target from the pad centre (m).
    place_jitter: float = 0.02
    #: Weights of the grasp score.
    score: GraspScoreConfig = field(default_factory=GraspScoreConfig)
    #: Firm-hold pinch: the block's centre this far (m) along the gripper y axis, between the pads of fingers 2 and 3
    #: (otherwise the hand's ``hand_y``, -5 mm; the 2-finger hand always centres it, ``grasping.hand``).
    pose_hand_y: float = -0.012


@settings
class ScoringConfig:
    """Success criteria and the failure taxonomy thresholds."""

    #: Grasp success: the block's bottom at least this high (m) for `hold_time`.
    lift_min: float = 0.05
    #: Grasp success: the block held up for this long (s).
    hold_time: float = field(default=1.0, metadata=within(0, 100))
    #: Place success: the block within this xy distance (m) of its target, released and at rest.
    place_tol: float = 0.025
    #: Place success: the hand at least this far (m) from the block.
    hand_away: float = 0.05
    #: The block is at rest below these speeds (m/s, rad/s).
    rest_speed: tuple[float, float] = (0.01, 0.2)
    #: The block is at rest after this many control periods in a row below `rest_speed`.
    rest_periods: int = field(default=3, metadata=within(1, 1000))
    #: Time (s) allowed for the block to come to rest after release.
    rest_timeout: float = field(default=1.5, metadata=within(0, 100))
    #: A failed episode counts as "pose error" when the target's ADD(-S) exceeds this x its diameter.
    pose_error_frac: float = 0.1
    #: Surface points of the block model for ADD and ADD-S.
    pose_error_points: int = field(default=500, metadata=within(1, 1000000))
    #: Oracle: blocks with fewer visible mask pixels (at 640x480) are not detected.
    min_visible_px: int = field(default=150, metadata=within(0, 10000000))


@settings
class FirmHoldConfig:
    """How the tasks that hold the block firmly (``TrialConfig.firm_hold_tasks``) do it: the yaw-stable pinch
    (``GraspConfig.pose_hand_y``) with all three fingers and MuJoCo's noslip solver, which removes the slip the soft
    contacts still allow (without it a 2x2 brick pinched by its top edge slid 9 mm down the fingers and turned
    10 deg during the carry: stack, seed 0, 7 of its 8 episodes failed; noslip costs about 15 % more physics)."""

    #: Once two fingers grip, control periods the fingers may close more until all three touch.
    finger_wait: int = field(default=10, metadata=within(0, 1000))
    #: Noslip solver iterations per physics step (0: off).
    noslip_iterations: int = field(default=2, metadata=within(0, 1000))


@settings
class TrialConfig:
    """One trial campaign: scenes of ``min_blocks``-``max_blocks`` blocks, control, grasps, scoring."""

    #: Fewest blocks in a scene.
    min_blocks: int = field(default=1, metadata=within(1, 200))
    #: Most blocks in a scene.
    max_blocks: int = field(default=5, metadata=within(1, 200))
    #: Hand-eye calibration file (`T_gripper_cam`) the planner uses (`posegrasp calibrate` writes it).
    hand_eye: str = str(HAND_EYE_JSON)
    #: Elliptic friction cones, so that grasped blocks do not creep out of the fingers.
    elliptic_cones: bool = True
    #: MuJoCo impedance ratio of the contacts (high: less creep in the fingers).
    impratio: float = field(default=10.0, metadata=within(0.001, 10000.0))
    #: Whether bodies at rest sleep after the scene settles (MuJoCo's sleeping islands: not simulated till touched).
    sleep: bool = True
    #: Speeds below which a body is at rest and may sleep (MuJoCo's ``sleep_tolerance``; its default).
    sleep_tolerance: float = field(default=1e-3, metadata=within(0.0, 1.0))
    #: Tasks that hold the block firmly (``firm_hold``); unset: the set's manifest's choice (imported sets: all; else
    #: kitting, stack and bin-pick).
    firm_hold_tasks: tuple[str, ...] | None = None
    #: How those tasks hold firmly.
    firm_hold: FirmHoldConfig = field(default_factory=FirmHoldConfig)
    #: MuJoCo solref time constant (s) of the table's and pad's contacts after settling (0.02 lets bricks walk).
    support_timeconst: float = field(default=0.01, metadata=within(0.0001, 1.0))
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
    #: The trial task (``--task``), one of ``grasping.tasks.TASKS``.
    task: str = "pick-place"
    #: The kitting task's settings.
    kitting: KittingConfig = field(default_factory=KittingConfig)
    #: The stack task's settings.
    stack: StackConfig = field(default_factory=StackConfig)
    #: The bin-picking task's settings.
    bin_pick: BinPickConfig = field(default_factory=BinPickConfig)
    #: Wall seconds a provider may take per capture, else "perception error"; 0: no limit.
    perception_timeout_s: float = field(default=60.0, metadata=within(0.0, 86400.0))
    #: Seconds a look waits for the provider's estimates, counted in the cycle time (picks per hour, ``compare``);
    #: unset: the provider's own figure (the oracles: 0), else the campaign's measured median (``grasping.latency``).
    perception_latency: float | None = field(default=None, metadata=within(0.0, 3600.0))


def firm_hold_tasks(cfg: TrialConfig) -> tuple[str, ...]:
    """The tasks that hold the block firmly: ``cfg.firm_hold_tasks``, else the object set's, else
    ``config.FIRM_HOLD_TASKS``."""
    from posegrasp.catalog import set_firm_hold_tasks

    if cfg.firm_hold_tasks is not None:
        return cfg.firm_hold_tasks
    tasks = set_firm_hold_tasks(cfg.scene.workcell.objects)
    return FIRM_HOLD_TASKS if tasks is None else tasks


def holds_firmly(cfg: TrialConfig) -> bool:
    """Does the campaign's task hold the block firmly (``firm_hold_tasks``, ``FirmHoldConfig``)?"""
    return cfg.task in firm_hold_tasks(cfg)


def config_record(cfg: TrialConfig) -> dict:
    """``cfg`` as ``campaign.json`` and a capture export record it: ``dataclasses.asdict``, the workcell's as
    ``sim.config.workcell_record`` keeps it (the suction tool's settings only for the suction hand)."""
    d = dataclasses.asdict(cfg)
    d["scene"]["workcell"] = workcell_record(d["scene"]["workcell"])
    return d


def load_trial_config(path: str | Path | None = None) -> TrialConfig:
    """Trial settings from a TOML file, or the defaults."""
    return load_toml(TrialConfig, path)
