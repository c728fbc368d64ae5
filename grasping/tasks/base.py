"""The trial task: what the robot must do in an episode, in which scene, and how it is judged.

A campaign (``posegrasp trials --task NAME``) runs one ``Task``, found by its name in ``grasping.tasks.REGISTRY``.
The campaign checks its settings once (``Task.check``); then, for every episode, the loop
(``grasping.episode.run_episode``) draws the episode's seeds, asks the task for its settled scene
(``Task.scene``) and its empty record (``Task.new_record``), sets up the arm and hands the running
``grasping.episode.Episode`` to ``Task.run``. ``run`` strings the episode's phases together, each a method of the
episode, which moves the simulated arm and fills in the record:

- ``look_down`` / ``look_and_perceive`` / ``capture`` / ``perceive``: drive the hand camera to a look, capture it
  and ask the perception provider for pose estimates (the planner sees the blocks only through them);
- ``plan``: choose a block among the estimates (those a predicate allows) and its best reachable grasp;
- ``pick``, ``lift_and_carry``, ``place``: close the fingers on it, carry it above a ``Goal`` (a point, a turn
  about the vertical, a surface height) and set it down;
- ``wait_for_rest``, ``released``: what a verdict needs to know after the hand has let go.

A phase that cannot go on raises ``EpisodeFailed`` with a ``record.Failure``; the loop catches it, writes the reason
into the record and counts a failure after a grasp on an estimate far off as a "pose error". A task's own verdicts
(``Failure.WRONG_FACE``, ...) are raised the same way. ``run`` returns normally on success.

Most tasks pick one block and set it down somewhere: they subclass ``PickTask``, whose ``run`` is that sequence,
and fill in its hooks (what to do before the pick, which estimates may be picked, the goal, the verdict, whether
to steady the arm). ``pick_place.py``, ``kitting.py`` and ``stack.py`` are the examples. A task whose episode
is a sequence of attempts writes its own ``run`` instead: bin picking, say, loops perceive / choose a part among
the estimates / pick / drop into an out-box until the tote is empty, K attempts in a row failed or 2N attempts
were made, catching ``EpisodeFailed`` per attempt; it keeps one record per attempt in a record type of its own
(an ``EpisodeRecord`` subclass declared with ``task=NAME``, which ``new_record`` then makes), builds its tote scene
in ``scene`` (with its own settings, e.g. ``bin`` or ``pile``) and declares what its campaign summary, a comparison
of two of its runs and its report page show (``metrics``, ``print_summary``, ``compare``, ``judged_by``,
``print_comparison``, ``report_page``): nothing outside the task compares its name. Such a task is a package
(``bin_pick/``).

Rules every task keeps:

- Determinism: everything random in an episode comes from the episode's seeds (the scene seed given to ``scene``,
  ``Episode.percept_seed``, ``Episode.place_offset`` and ``Episode.seed_for(j)`` for further draws), never from
  global state, so a record never depends on the worker count or on a resume.
- Units and frames: SI units (m, rad, s; degrees only where a name says ``_deg``), poses ``T_world_obj`` 4x4.
- Settings: a task's settings are a ``@settings`` class in its module, every field with a one-line ``#:``
  description, held by ``TrialConfig`` under the task's name (TOML section ``[kitting]``, ``[stack]``).
- Captures: ``looks`` lists the ``Observation.im_id`` of every capture an episode takes, so exports and replays
  of BOP results (``--export-captures``, ``--perception bop-csv:``) know the frames.

To add a task: write its module here (settings class, scene, a ``Task`` subclass), add it to ``REGISTRY`` in
``grasping/tasks/__init__.py`` (the ``--task`` choices) and its settings to ``TrialConfig``.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
from rich.console import Console

from posegrasp.catalog import PartType, load_catalog
from posegrasp.config import settings
from posegrasp.errors import PosegraspError, UserError
from posegrasp.grasping.perception import PICK_LOOK
from posegrasp.grasping.record import EpisodeRecord, Failure
from posegrasp.grasping.tables import print_episodes, print_per_block
from posegrasp.sim.workcell import Workcell

if TYPE_CHECKING:
    from posegrasp.executor import Executor
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping.episode import Episode
    from posegrasp.grasping.report.run import TrialRun
    from posegrasp.grasping.targets import Plan

#: Height (m) of the place pad's surface.
PAD_TOP = 0.003

#: Which estimates a task may pick: ``pickable(block, T_world_obj)`` of an estimate's type and levelled pose.
Pickable = Callable[[PartType, np.ndarray], bool]
#: ``graspable(wc, k)``: does the grasp planner find scene block ``k`` (1-based) a yaw-stable grasp clear of its
#: neighbours, at their true poses (given to ``Task.scene``, which may want a scene with something to pick)?
Graspable = Callable[[Workcell, int], bool]


class EpisodeFailed(PosegraspError):
    """Ends an episode with the failure ``reason`` (raised by the episode's phases and the tasks' verdicts, caught
    by the episode's loop: it never reaches the command line)."""

    def __init__(self, reason: Failure):
        super().__init__(reason.value)
        self.reason = reason


@dataclass(frozen=True)
class Goal:
    """Where a carried block is set down: its centre over ``xy`` (world, m), turned by ``yaw`` (rad) about the
    vertical while carried, its bottom onto a surface at height ``surface_z`` (m)."""

    xy: np.ndarray
    yaw: float = 0.0
    surface_z: float = PAD_TOP


@settings
class SteadyConfig:
    """A steadied pick and place: the arm stops swaying (5-8 mm after a fast descent) before the fingers close and
    before the block is set down, approaches slowly, and lowers the block from higher up (guarded, slowly), so a
    block that slid down in the fingers touches its surface slowly too. The controller keeps a steady offset of
    1-1.5 mm from its target, so a distance to the target does not tell a still arm: its speed does."""

    #: The arm is still once the gripper has moved slower than this (m/s) for 3 control periods in a row ...
    settle_speed: float = 0.005
    #: ... waiting at most this long (s) for it.
    settle_time: float = 1.0
    #: The block is brought this far (m) above its surface before the slow, guarded descent (``grasp.place_gap``
    #: otherwise).
    place_gap: float = 0.02
    #: Peak speed (m/s) of the approach and the place descent (else ``grasp.approach_speed``, which sways the arm).
    approach_speed: float = 0.1


class Task(ABC):
    """A trial task (the module docstring says how the pieces fit). A task names itself, its looks, its scene and
    its episode (``scene``, ``run``), and what its campaign summary, a comparison of two of its runs and its report
    page show; the defaults are the table tasks' (one target per episode, success or failure)."""

    #: The ``--task`` name.
    name: str = ""
    #: The ``Observation.im_id`` of every capture an episode takes (``perception.PICK_LOOK``, ...).
    looks: tuple[int, ...] = (PICK_LOOK,)
    #: Can it pick with the suction tool (``--hand suction``)?
    suction: bool = False
    #: The type of its episodes' records (registered for reading: ``record.RECORD_TYPES``).
    record_type: type[EpisodeRecord] = EpisodeRecord

    @property
    def fixed_looks(self) -> tuple[int, ...]:
        """The looks whose frames do not depend on what the robot did before them: those a ``--captures-only``
        run takes (all of ``looks`` but in a task whose later looks follow its picks)."""
        return self.looks

    def blocks(self, cfg: TrialConfig) -> tuple[int, int]:
        """Fewest and most blocks of an episode's scene (its count is drawn uniformly between them):
        ``TrialConfig.min_blocks`` and ``max_blocks``."""
        return cfg.min_blocks, cfg.max_blocks

    def with_scene(self, cfg: TrialConfig, scene: str | None, blocks: int | None) -> TrialConfig:
        """``cfg`` with ``--scene`` and ``--blocks`` (None: not given): the table only, ``blocks`` per episode."""
        if scene not in (None, "table"):
            raise UserError(f"--scene {scene} is a bin-picking scene: use it with --task bin-pick (the {cfg.task} "
                            "task runs on the table)")
        return dataclasses.replace(cfg, min_blocks=blocks, max_blocks=blocks) if blocks else cfg

    def check(self, cfg: TrialConfig) -> None:
        """A one-line UserError, naming the setting to change, unless the campaign's settings can serve the task
        (kitting needs a block type with an upright face, ...); every campaign's by default."""

    @abstractmethod
    def scene(self, cfg: TrialConfig, seed: int, n_blocks: int, graspable: Graspable) -> Workcell:
        """The episode's settled scene of ``n_blocks`` blocks to pick, drawn from ``seed`` only;
        ``SceneUnsettled`` when no draw settles (recorded as a simulation error)."""

    def new_record(self, episode: int, seed: int, scene_seed: int, n_blocks: int, perception: str) -> EpisodeRecord:
        """The episode's record, before anything ran (a ``record_type``), naming the task."""
        return self.record_type(episode, seed, scene_seed, n_blocks, perception, task=self.name)

    @abstractmethod
    def run(self, ep: Episode) -> None:
        """The episode after its scene: its phases in order, filling in ``ep.rec``; raises ``EpisodeFailed``."""

    def metrics(self, records: list[dict], latency: float = 0.0) -> dict:
        """The task's own entries of the campaign summary, over its episodes' JSON records and the campaign's
        perception ``latency`` (s per look, ``grasping.latency``); none beyond ``grasping.stats.summarise``'s by
        default."""
        return {}

    def print_summary(self, summary: dict, console: Console) -> None:
        """The campaign summary's terminal lines: the episodes' success rate, per block and per failure."""
        print_episodes(summary, console)

    def compare(self, a: dict[int, dict], b: dict[int, dict], common: list[int],
                latency: tuple[float, float] = (0.0, 0.0)) -> dict:
        """The task's own entries of a comparison of two runs' JSON records on their ``common`` episodes, with
        each run's perception ``latency`` (s per look; ``grasping.compare``; none by default)."""
        return {}

    def judged_by(self, result: dict) -> tuple[float, float]:
        """What ``compare --fail-if-worse`` judges: the difference B - A (negative: B is worse) and its p-value;
        by default the episodes' success rate and McNemar's exact test."""
        return result["difference"], result["mcnemar"]["p_value"]

    def print_comparison(self, result: dict, console: Console) -> None:
        """A comparison's terminal lines after the episodes' success rates: success per target block type."""
        print_per_block(result, console)

    def report_page(self, run: TrialRun, samples: int, executor: Executor | None) -> str | None:
        """The task's own report page (HTML) of ``run``, showing up to ``samples`` episodes; None: the table
        tasks' page (``report.page``)."""
        return None


class PickTask(Task):
    """A task that picks one block and sets it down: ``run`` is the sequence look and perceive, plan, pick, lift
    and carry to the ``goal``, place, ``judge``; subclasses fill in the hooks (``scene`` and ``judge`` at least)."""

    #: The failure when perception found blocks but ``pickable`` allows none of them.
    unpickable: Failure = Failure.UNREACHABLE

    def run(self, ep: Episode) -> None:
        context = self.prepare(ep)
        ests = ep.look_and_perceive()
        if ep.captures_only:
            return
        plan = ep.plan(ests, self.pickable(ep, context), self.unpickable)
        goal = self.goal(ep, plan, context)
        steady = self.steady(ep.cfg)
        ep.pick(plan, steady)
        ep.place(plan, ep.lift_and_carry(plan, goal, steady), steady)
        self.judge(ep, plan, context)

    def prepare(self, ep: Episode) -> Any:
        """What the task does before the look at the pick area; returns what the later hooks need (None)."""
        return None

    def pickable(self, ep: Episode, context: Any) -> Pickable | None:
        """Which estimates may be picked (None: any)."""
        return None

    def goal(self, ep: Episode, plan: Plan, context: Any) -> Goal:
        """Where the planned block is set down: over the episode's place point, as it is."""
        return Goal(ep.place_xy)

    def steady(self, cfg: TrialConfig) -> SteadyConfig | None:
        """How to steady the arm around the grasp and the place (None: no steadying)."""
        return None

    @abstractmethod
    def judge(self, ep: Episode, plan: Plan, context: Any) -> None:
        """After the hand has let go: the verdict, recorded; ``EpisodeFailed`` unless the task succeeded."""


def task_types(cfg: TrialConfig) -> list[PartType]:
    """The block types the task's scenes draw from (the scene's ``block_types``, or its whole object set)."""
    cat = load_catalog(cfg.scene.workcell.objects)
    return [cat[n] for n in cfg.scene.block_types if n in cat] if cfg.scene.block_types else list(cat.values())
