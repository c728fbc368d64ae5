"""The bin-picking task: one episode empties one tote (``--scene bin``) or one heap on the table (``--scene pile``)
into an out-box beside it, attempt after attempt.

Each attempt looks down at the tote from above (capture ``im_id`` = the attempt's index), perceives, chooses the
next part among the estimates, picks it with a grasp clear of the tote's walls, the neighbours' estimated surfaces
and the depth image, lifts it clear of the walls and drops it into the out-box (``grasping.bin_picking``). The
episode ends when the robot sees nothing left to pick, when it sees again what it saw when it found no grasp on any
part (that look is no attempt), after ``max_failures`` failed attempts in a row, or after
``attempts_per_part`` attempts per part present. Every attempt is recorded (``record.Attempt``); the episode's
record (``record.BinPickRecord``) says how many parts went into the out-box.

Its scene: ``sim.clutter``'s heap of parts (``ClutterConfig.parts``, drawn per episode) settled in the tote or on
the table, and the out-box (a tote of its own, ``outbox``) on the place area. Its summary (``metrics``): percent
cleared per episode (mean, t 95 % interval), attempt success (Wilson 95 %), grasp success (the attempts that went
for a part: VGN's grasp success rate, where a look that finds no grasp is no grasp), picks per simulated hour, attempt
failures by reason, success by part type and by the target's visible fraction.
"""

from __future__ import annotations

import math
import statistics
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np
from dm_control import mjcf

from posegrasp.config import within
from posegrasp.errors import ConfigError, UserError
from posegrasp.grasping.record import BIN_PICK, BinPickRecord, EpisodeRecord
from posegrasp.grasping.tasks.base import Graspable, task_types
from posegrasp.sim.clutter import CLUTTER_KINDS, ClutterConfig, build_clutter_scene, check_clutter, clutter_workcell
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.scene import choose_types
from posegrasp.sim.tote import Tote, ToteConfig
from posegrasp.sim.workcell import BlockInstance, Workcell

if TYPE_CHECKING:
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping.episode import Episode

#: Model name of the out-box: the prefix of its geoms' names in a workcell.
OUTBOX = "outbox"
#: The ``im_id`` of every capture a bin-picking episode may take: one per attempt, at most twice the most parts.
BIN_LOOKS = tuple(range(2 * int(ClutterConfig.__dataclass_fields__["max_parts"].metadata["range"][1])))
#: Visible-fraction bins of the summary: (label, low, high), low <= fraction < high.
VISIBILITY_BINS = (("<0.5", 0.0, 0.5), ("0.5-0.9", 0.5, 0.9), (">=0.9", 0.9, math.inf))


@dataclass(frozen=True)
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
    #: The out-box the parts are dropped into, centred on the place area.
    outbox: ToteConfig = field(default_factory=lambda: ToteConfig(inner_size=(0.14, 0.14), wall_height=0.05))
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
    #: The fingers open this much wider than the part they grasp (m; ``grasp.finger_margin`` on the table).
    finger_margin: float = field(default=0.01, metadata=within(0.0, 0.1))
    #: The open hand keeps this distance (m) from the other parts' estimated surfaces and the depth image's points
    #: (negative: it may push into the heap that far); from the walls it keeps ``grasp.clearance_min``. Tried in
    #: order: the next, looser value only when no part has a grasp (or none reachable) at the one before.
    part_clearance: tuple[float, ...] = (-0.008, -0.015)
    #: A grasp whose open fingers would touch a wall is tried again with the hand moved this far (m) along the
    #: gripper y axis (nearest first), the part sitting off-centre in the hand ...
    wall_shifts: tuple[float, ...] = (-0.024, -0.02, -0.016, -0.012, -0.008, -0.004, 0.004, 0.008, 0.012, 0.016, 0.02,
                                      0.024)
    #: ... while its contact faces still meet finger 1's pad and finger 2's or 3's this far (m) along y ...
    shift_contact: float = field(default=0.016, metadata=within(0.0, 0.05))
    #: ... and the fingers and the camera keep this far (m) from the walls (more than ``grasp.clearance_min``:
    #: neighbours push the descending fingers sideways, and off-centre they are nearer a wall).
    shift_clearance: float = field(default=0.008, metadata=within(0.0, 0.05))
    #: A grasp that no shift clears of the walls is tried again with the hand turned about its pinch point by the
    #: least of these (deg) that clears it (about the squeeze axis or across it, its top leaning away from the wall;
    #: its score losing ``grasp.score.tilt`` per degree) ...
    wall_tilts_deg: tuple[float, ...] = (10.0, 20.0)
    #: ... raised until the open fingers keep this far (m) above the floor.
    tilt_floor_clearance: float = field(default=0.002, metadata=within(0.0, 0.05))
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


def outbox_of(workcell: WorkcellConfig, cfg: BinPickConfig) -> Tote:
    """The out-box of ``cfg``, centred on the workcell's place area."""
    return Tote(cfg.outbox, tuple(float(c) for c in workcell.place_area.center))


def add_outbox(box: Tote) -> Callable[[mjcf.RootElement], None]:
    """``extras(root)`` for a workcell: attach the out-box ``box`` (geoms ``outbox/floor``, ``outbox/wall_x0``, ...)."""

    def add(root: mjcf.RootElement) -> None:
        model = box.mjcf_model()
        model.model = OUTBOX
        root.attach(model).pos = (*box.center, 0.0)

    return add


def bin_workcell(cfg: TrialConfig, parts: list[BlockInstance]) -> Workcell:
    """The campaign's bin or pile workcell with ``parts`` (parked until dropped) and the out-box."""
    b = cfg.bin_pick
    return clutter_workcell(cfg.scene.workcell, b.scene, parts, b.clutter,
                            extras=add_outbox(outbox_of(cfg.scene.workcell, b)))


def bin_scene(cfg: TrialConfig, seed: int, n_parts: int) -> Workcell:
    """A settled heap of ``n_parts`` parts (types and colours drawn from ``seed``) in the tote or on the table."""
    rng = np.random.default_rng(seed)
    types = choose_types(cfg.scene, n_parts, rng)
    colours = [cfg.scene.palette[i] for i in rng.integers(0, len(cfg.scene.palette), size=n_parts)]
    wc = bin_workcell(cfg, [BlockInstance(t, (*c, 1.0)) for t, c in zip(types, colours)])
    build_clutter_scene(wc, cfg.bin_pick.scene, cfg.bin_pick.clutter, rng)
    return wc


def mean_ci95(values: list[float], lo: float = -math.inf, hi: float = math.inf) -> dict:
    """Mean of ``values`` with its Student-t 95 % interval, clipped to [``lo``, ``hi``] (None for fewer than 2
    values)."""
    n = len(values)
    if n == 0:
        return {"n": 0, "mean": None, "ci95": None}
    mean = statistics.fmean(values)
    if n < 2:
        return {"n": n, "mean": mean, "ci95": None}
    from scipy.stats import t

    half = float(t.ppf(0.975, n - 1)) * statistics.stdev(values) / math.sqrt(n)
    return {"n": n, "mean": mean, "ci95": [max(lo, mean - half), min(hi, mean + half)]}


def visibility_bin(fraction: float | None) -> str:
    """The ``VISIBILITY_BINS`` label of a visible fraction ("unknown": none measured)."""
    if fraction is None:
        return "unknown"
    return next(label for label, lo, hi in VISIBILITY_BINS if lo <= fraction < hi)


def bin_metrics(records: list[dict]) -> dict:
    """Bin picking's summary entries over its episodes' JSON records (``BinPickTask.metrics``)."""
    from posegrasp.grasping.stats import rate_row

    eps = [r for r in records if r.get("task") == BIN_PICK]
    attempts = [a for r in eps for a in r.get("attempts", [])]
    ok = [a["outcome"] == "success" for a in attempts]
    went = [s for a, s in zip(attempts, ok) if a.get("target")]  # the robot went for a part (or a false detection)
    by_type: dict[str, list[bool]] = defaultdict(list)
    by_vis: dict[str, list[bool]] = defaultdict(list)
    for a, s in zip(attempts, ok):
        if a.get("target"):
            by_type[a["target"].get("type", "(no part there)")].append(s)
            by_vis[visibility_bin(a.get("visib_fract"))].append(s)
    sim_hours = sum(r["sim_time"] for r in eps) / 3600.0
    labels = [label for label, _, _ in VISIBILITY_BINS] + ["unknown"]
    return {"bin_pick": {
        "percent_cleared": mean_ci95([100.0 * r["cleared"] for r in eps], 0.0, 100.0),
        "episodes_cleared": sum(r["outcome"] == "success" for r in eps),
        "parts_present": sum(r["n_blocks"] for r in eps),
        "parts_removed": sum(r["removed"] for r in eps),
        "attempts": rate_row(sum(ok), len(ok)),
        "grasps": rate_row(sum(went), len(went)),
        "picks": sum(ok),
        "sim_hours": sim_hours,
        "picks_per_sim_hour": sum(ok) / sim_hours if sim_hours > 0 else None,
        "attempt_failures": dict(sorted(Counter(a["failure"] for a in attempts if a.get("failure")).items())),
        "episode_ends": dict(sorted(Counter(r["failure"] or "cleared" for r in eps).items())),
        "per_type": {t: rate_row(sum(v), len(v)) for t, v in sorted(by_type.items())},
        "per_visibility": {b: rate_row(sum(by_vis[b]), len(by_vis[b])) for b in labels if by_vis.get(b)},
    }}


class BinPickTask:
    """Empty a tote (or a pile) into the out-box, attempt after attempt (a ``Task``; the module docstring)."""

    name = BIN_PICK
    looks = BIN_LOOKS
    fixed_looks = BIN_LOOKS[:1]  # the first look only: the later ones follow the picks
    firm_hold = True

    def blocks(self, cfg: TrialConfig) -> tuple[int, int]:
        """``bin_pick.clutter.parts``."""
        lo, hi = cfg.bin_pick.clutter.parts
        return lo, hi

    def check(self, cfg: TrialConfig) -> None:
        """A one-line UserError for a scene that is no heap, a part count the tote cannot hold, a part too big
        for the hand or a tote the hand cannot reach."""
        b = cfg.bin_pick
        if b.scene not in CLUTTER_KINDS:
            raise ConfigError(f"task bin-pick needs scene bin or pile, not {b.scene!r} (--scene, bin_pick.scene)")
        lo, hi = b.clutter.parts
        if not 1 <= lo <= hi:
            raise ConfigError(f"bin_pick.clutter.parts must be 1 <= min <= max, got {list(b.clutter.parts)}")
        if not b.part_clearance or not all(-0.05 <= c <= 0.1 for c in b.part_clearance):
            raise ConfigError(f"bin_pick.part_clearance must be one or more distances (m) in [-0.05, 0.1], got "
                              f"{list(b.part_clearance)}")
        if not all(0.0 < t <= 40.0 for t in b.wall_tilts_deg):
            raise ConfigError(f"bin_pick.wall_tilts_deg must be angles (deg) in (0, 40], got {list(b.wall_tilts_deg)}")
        types = task_types(cfg)
        too_big = [t.name for t in types if float(np.min(t.extents)) > cfg.grasp.max_width]
        if too_big:
            raise UserError(f"part(s) {too_big} are wider than the hand opens ({cfg.grasp.max_width} m, "
                            "grasp.max_width) every way: choose other scene.block_types or --objects")
        check_clutter(cfg.scene.workcell, b.scene, b.clutter, types, hi)

    def scene(self, cfg: TrialConfig, seed: int, n_blocks: int, graspable: Graspable) -> Workcell:
        return bin_scene(cfg, seed, n_blocks)

    def new_record(self, episode: int, seed: int, scene_seed: int, n_blocks: int, perception: str) -> EpisodeRecord:
        return BinPickRecord(episode, seed, scene_seed, n_blocks, perception, task=self.name)

    def run(self, ep: Episode) -> None:
        """Attempts until the tote is believed empty (``Episode.empty_tote``: ``grasping.bin_picking``)."""
        ep.empty_tote()

    def metrics(self, records: list[dict]) -> dict:
        return bin_metrics(records)
