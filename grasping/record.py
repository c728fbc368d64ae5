"""What one grasp-and-place episode records: the typed ``EpisodeRecord`` (a line of ``episodes.jsonl``), its
failure taxonomy and its phase timings (a line of ``timings.jsonl``).

Lengths in metres, angles in degrees where the name says ``_deg``, times in simulated seconds (wall-clock and
CPU seconds only in ``EpisodeTimings``). ``to_json()`` gives the JSON-ready dict: floats rounded to 6 decimals;
``EpisodeRecord.from_json`` reads such a dict back.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from enum import StrEnum

from posegrasp.config import from_dict
from posegrasp.errors import UserError
from posegrasp.grasping.upright import UprightDeviation
from posegrasp.io import jsonable



class Failure(StrEnum):
    """Why an episode (or a bin-picking attempt) failed, in the order the summary lists them; a record's
    ``failure`` holds the value (text). ``NO_UPRIGHT``-``BASE_MOVED`` come from the kitting and stack tasks, the rest
    after them from bin picking (``grasping.tasks.bin_pick``): its attempts' reasons, then its episodes' ends."""

    NO_DETECTION = "no detection"  # the provider returned no estimate
    PERCEPTION_ERROR = "perception error"  # the provider raised, hung or returned what the planner cannot use
    POSE_ERROR = "pose error"  # the chosen estimate was no block, or a later failure on an estimate too far off
    UNREACHABLE = "unreachable"  # no grasp of an acceptable estimate passed the IK check
    COLLISION = "collision"  # the hand hit the table or another block on its way to the grasp
    SLIP = "slip"  # the fingers did not close on the block, or it left them before the hold time
    DROP = "drop"  # the block fell out of the hand after the grasp was scored
    MISPLACED = "misplaced"  # the block ended too far from its target, moving, or still touched by the hand
    TIMEOUT = "timeout"  # the arm did not reach a pose in time
    SIMULATION_ERROR = "simulation error"  # the physics diverged, or the scene never came to rest
    NO_UPRIGHT = "no upright block"  # the task allows none of the estimates (none believed upright)
    NO_BASE = "no base seen"  # stack: perception found no base on the pad
    WRONG_FACE = "wrong face up"  # the placed block's upright face is not down
    MISALIGNED = "misaligned"  # the placed block's yaw is off its target's
    BASE_MOVED = "base moved"  # stack: the base moved
    NOTHING_GRASPABLE = "nothing graspable"  # bin: parts were seen, none with a grasp clear of walls and neighbours
    WALL_HIT = "hit the wall"  # bin: the robot touched the tote's walls (a protective stop)
    DOUBLE_PICK = "two parts lifted"  # bin: another part came out of the tote with the target
    THROWN_OUT = "part thrown out"  # bin: a part left the tote other than into the out-box
    NO_SEAL = "no seal"  # bin, suction: the cup's rim did not seal on the part
    SEAL_LOST = "seal lost"  # bin, suction: the vacuum let the part go in the lift or the carry
    ROLLED = "rolled off a wall"  # bin, hybrid: the closed fingers rolled a round part off a wall, picking nothing
    NO_SLOT = "no free slot"  # bin, tray: parts were seen, none of a type with a free slot left in the tray
    PARTS_LEFT = "parts left"  # bin episode: the robot saw nothing more to pick, yet parts were not removed
    FAILED_IN_A_ROW = "failed in a row"  # bin episode: ended after too many failed attempts in a row
    ATTEMPT_LIMIT = "attempt limit"  # bin episode: ended after its most attempts (twice the parts)


#: The failure reasons (values of ``Failure``), in the order the summary lists them.
FAILURES = tuple(Failure)
#: Failures never re-counted as "pose error" (``grasping.episode``): nothing was grasped, or the task's own verdict.
NOT_POSE_ERRORS = frozenset({Failure.NO_DETECTION, Failure.SIMULATION_ERROR, Failure.NO_UPRIGHT, Failure.NO_BASE,
                             Failure.WRONG_FACE, Failure.MISALIGNED, Failure.BASE_MOVED, Failure.NOTHING_GRASPABLE,
                             Failure.ROLLED, Failure.PARTS_LEFT, Failure.FAILED_IN_A_ROW, Failure.ATTEMPT_LIMIT})
#: Record fields of the kitting and stack tasks, left out of a pick-and-place record.
TASK_FIELDS = ("task", "estimate_error", "final_error", "base")
#: Record types by task name: an ``EpisodeRecord`` subclass declared with ``task=NAME`` registers itself here, and
#: ``EpisodeRecord.from_json`` reads a record of that task as one (the tasks' modules, ``grasping.tasks``, define
#: them; a campaign, ``compare`` and ``report`` load the tasks before they read records).
RECORD_TYPES: dict[str, type[EpisodeRecord]] = {}


@dataclass(frozen=True)
class Target:
    """The scene block the planner went for (``instance``, 1-based) and the grasp it chose on it."""

    instance: int
    type: str  # the block's catalogue name
    class_ok: bool  # did perception give the block's true class?
    diameter: float
    grasp_width: float  # span across the fingers (m; the suction cup: its diameter)
    clearance: float  # the hand's clearance from the neighbours (m)
    support: float  # flatness of the contact faces (0-0.5; the suction cup: its seal margin, m)
    tilt_deg: float  # approach direction's angle from straight down


@dataclass(frozen=True)
class FalseTarget:
    """The chosen estimate matched no block of the scene (a false detection of class ``obj_id``)."""

    instance: int  # always 0: no scene block
    obj_id: int


@dataclass(frozen=True)
class PoseDeviation:
    """The target estimate's error against ground truth: translation (m), rotation (deg), ADD and ADD-S (m);
    ``err`` is the one named by ``metric`` (ADD-S for symmetric blocks)."""

    te: float
    re_deg: float
    add: float
    adds: float
    metric: str
    err: float


@dataclass(frozen=True)
class BaseRecord:
    """The stack task's base block: scene ``instance`` (1-based), type, its estimate's error against ground
    truth modulo symmetries (None if perception found no base) and how far it moved during the episode (m)."""

    instance: int
    type: str
    estimate_error: UprightDeviation | None = None
    shift: float | None = None


@dataclass
class EpisodeRecord:
    """One episode's deterministic outcome, filled in as its phases run."""

    episode: int
    seed: int  # the campaign seed
    scene_seed: int
    n_blocks: int
    perception: str
    blocks: list[str] = field(default_factory=list)  # catalogue names of the scene's blocks
    target: Target | FalseTarget | None = None
    outcome: str = "failure"  # or "success"
    failure: Failure | None = None
    grasped: bool = False
    placed: bool = False
    pose_error: PoseDeviation | None = None
    place_error: float | None = None  # the block's xy distance from its place target (m)
    detected: int = 0  # estimates the provider returned
    sim_time: float = 0.0
    phases: dict[str, float] = field(default_factory=dict)  # simulated seconds per phase
    task: str | None = None  # the task's name (None: a pick-and-place record written before records named it)
    estimate_error: UprightDeviation | None = None  # the target's estimate against ground truth, modulo symmetries
    final_error: UprightDeviation | None = None  # the placed block against the task's target, modulo symmetries
    base: BaseRecord | None = None  # stack: the base block
    perception_error: str | None = None  # "perception error": what the provider did wrong (one line)

    def __init_subclass__(cls, task: str | None = None, **kwargs) -> None:
        """Register ``cls`` as the record type of the task named ``task`` (``RECORD_TYPES``)."""
        super().__init_subclass__(**kwargs)
        if task is not None:
            RECORD_TYPES[task] = cls

    def to_json(self) -> dict:
        """The ``episodes.jsonl`` record (``perception_error`` only when set; none of ``TASK_FIELDS`` in a
        pick-and-place record of before records named their task)."""
        d = dataclasses.asdict(self)
        if self.task is None:
            for k in TASK_FIELDS:
                del d[k]
        if self.perception_error is None:
            del d["perception_error"]
        if self.failure is not None:
            d["failure"] = Failure(self.failure).value
        return jsonable(d, digits=6)

    @classmethod
    def from_json(cls, data: dict, where: str = "episode record") -> EpisodeRecord:
        """The record of an ``episodes.jsonl`` line (``to_json``'s inverse); a UserError naming ``where`` and
        the key for a missing, unknown or mistyped field."""
        if not isinstance(data, dict):
            raise UserError(f"{where}: expected a JSON object, got {type(data).__name__}")
        missing = [f.name for f in dataclasses.fields(cls) if f.name not in data
                   and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
        missing += [k for k in ("outcome",) if k not in data]  # written by every record, though it has a default
        if missing:
            raise UserError(f"{where}: missing field(s) {missing}")
        check_outcome(data, where)
        if cls is EpisodeRecord and RECORD_TYPES.get(data.get("task") or "pick-place", cls) is not cls:
            return RECORD_TYPES[data.get("task") or "pick-place"].from_json(data, where)
        rec = from_dict(cls, {k: v for k, v in data.items() if k != "target"}, where)
        rec.target = read_target(data.get("target"), f"{where}.target")
        return rec


def check_outcome(data: dict, where: str) -> None:
    """A one-line UserError unless ``data`` (a record) has ``outcome`` "success" or "failure" and a ``failure``
    that is None or one of ``Failure``'s reasons."""
    outcome, failure = data.get("outcome"), data.get("failure")
    if outcome not in ("success", "failure"):
        raise UserError(f"{where}: outcome = {json.dumps(outcome)[:40]} is not \"success\" or \"failure\"")
    if failure is not None and failure not in {f.value for f in Failure}:
        raise UserError(f"{where}: failure = {json.dumps(failure)[:40]} is not null or one of the failure reasons "
                        f"({', '.join(f.value for f in Failure)})")


def read_target(data: object, where: str) -> Target | FalseTarget | None:
    """A record's ``target`` read back from JSON (None stays None)."""
    if data is None:
        return None
    return from_dict(FalseTarget if isinstance(data, dict) and "obj_id" in data else Target, data, where)


@dataclass(frozen=True)
class EpisodeTimings:
    """Wall-clock and CPU seconds per phase of one episode (they vary run to run)."""

    episode: int
    wall_s: dict[str, float]
    cpu_s: dict[str, float]

    def to_json(self) -> dict:
        """The ``timings.jsonl`` record."""
        return jsonable(dataclasses.asdict(self), digits=6)
