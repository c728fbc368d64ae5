"""Bin picking's records: one ``Attempt`` per look at the tote, gathered in the episode's ``BinPickRecord`` (a
line of ``episodes.jsonl``). Lengths in metres, times in simulated seconds."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from posegrasp.config import from_dict
from posegrasp.errors import UserError
from posegrasp.grasping.record import EpisodeRecord, FalseTarget, Failure, PoseDeviation, Target, read_target
from posegrasp.grasping.tasks.bin_pick.config import BIN_PICK
from posegrasp.io import jsonable


@dataclass
class Attempt:
    """One bin-picking attempt: look, perceive, choose a part, pick it and drop it into the out-box (or, the hybrid
    hand, roll it off a wall: ``roll.py``, failure "rolled off a wall"). ``attempt`` (0-based) is also the ``im_id``
    of its capture."""

    attempt: int
    outcome: str = "failure"  # or "success": the target, alone, ended in the out-box (in its slot, within tolerance)
    failure: Failure | None = None
    detected: int = 0  # estimates the provider returned
    target: Target | FalseTarget | None = None
    pose_error: PoseDeviation | None = None  # the target's estimate against its true pose
    visib_fract: float | None = None  # the target's visible share of its unoccluded silhouette at the capture
    grasped: bool = False  # the target was lifted clear of the tote's walls and held
    removed: list[int] = field(default_factory=list)  # parts (1-based) that went into the out-box
    thrown_out: list[int] = field(default_factory=list)  # parts (1-based) that left the tote elsewhere
    sim_time: float = 0.0  # simulated seconds the attempt took
    slot: int | None = None  # tray: the slot (0-based) the target was set down in
    place_error: dict | None = None  # tray: the target at rest against its slot (``tray.PlaceError``: m, deg)
    in_hand: dict | None = None  # tray's second look: whether it saw the part, its change to the held pose (m, deg)
    shaken: bool = False  # after finding nothing graspable, the tote was shaken (``BinPickConfig.shakes``)

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        if self.failure is not None:
            d["failure"] = Failure(self.failure).value
        for key in ("slot", "place_error", "in_hand"):  # the tray's: an out-box record has none
            if d[key] is None:
                del d[key]
        if not self.shaken:
            del d["shaken"]
        return d


@dataclass
class BinPickRecord(EpisodeRecord, task=BIN_PICK):
    """A bin-picking episode: a tote (or a pile) of ``n_blocks`` parts emptied attempt by attempt. ``outcome`` is
    "success" when every part went into the out-box, else ``failure`` says how the episode ended (the last
    attempt's reason after a simulation error); ``sim_time`` is the robot's simulated time."""

    removed: int = 0  # parts in the out-box (or on the tray) at the end
    cleared: float = 0.0  # removed / n_blocks
    attempts: list[Attempt] = field(default_factory=list)
    place: str = "out-box"  # where the parts went (``BinPickConfig.place``); an out-box record leaves it out

    def to_json(self) -> dict:
        d = super().to_json()
        d["attempts"] = [jsonable(a.to_json(), digits=6) for a in self.attempts]
        if self.place == "out-box":
            del d["place"]
        return d

    @classmethod
    def from_json(cls, data: dict, where: str = "episode record") -> BinPickRecord:
        rec = super().from_json({k: v for k, v in data.items() if k != "attempts"}, where)
        attempts = data.get("attempts") or []
        if not isinstance(attempts, list):
            raise UserError(f"{where}.attempts: expected a list, got {type(attempts).__name__}")
        rec.attempts = []
        for i, a in enumerate(attempts):
            at = f"{where}.attempts[{i}]"
            if not isinstance(a, dict):
                raise UserError(f"{at}: expected a JSON object, got {type(a).__name__}")
            att = from_dict(Attempt, {k: v for k, v in a.items() if k != "target"}, at)
            att.target = read_target(a.get("target"), f"{at}.target")
            rec.attempts.append(att)
        return rec
