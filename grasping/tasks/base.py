"""The trial task protocol: what the robot must do in an episode, in which scene, and how it is judged.

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
(``new_record``: an ``EpisodeRecord`` subclass with an ``attempts`` list, say), builds its tote scene in ``scene``
(with its own settings, e.g. ``bin`` or ``pile``) and adds its metrics to the campaign summary (``metrics``).

Rules every task keeps:

- Determinism: everything random in an episode comes from the episode's seeds (the scene seed given to ``scene``,
  ``Episode.percept_seed``, ``Episode.place_offset`` and ``Episode.seed_for(j)`` for further draws), never from
  global state, so a record never depends on the worker count or on a resume.
- Units and frames: SI units (m, rad, s; degrees only where a name says ``_deg``), poses ``T_world_obj`` 4x4.
- Settings: a task's settings are a frozen dataclass in its module, every field with a one-line ``#:``
  description, held by ``TrialConfig`` under the task's name (TOML section ``[kitting]``, ``[stack]``).
- Captures: ``looks`` lists the ``Observation.im_id`` of every capture an episode takes, so exports and replays
  of BOP results (``--export-captures``, ``--perception bop-csv:``) know the frames.

To add a task: write its module here (settings dataclass, scene, ``Task``), add it to ``REGISTRY`` in
``grasping/tasks/__init__.py`` (the ``--task`` choices) and its settings to ``TrialConfig``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Protocol

import numpy as np

from posegrasp.catalog import PartType, load_catalog
from posegrasp.grasping.perception import PICK_LOOK
from posegrasp.grasping.record import EpisodeRecord, Failure
from posegrasp.sim.workcell import Workcell

if TYPE_CHECKING:
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping.episode import Episode
    from posegrasp.grasping.targets import Plan

#: Height (m) of the place pad's surface.
PAD_TOP = 0.003

#: Which estimates a task may pick: ``pickable(block, T_world_obj)`` of an estimate's type and levelled pose.
Pickable = Callable[[PartType, np.ndarray], bool]
#: ``graspable(wc, k)``: does the grasp planner find scene block ``k`` (1-based) a yaw-stable grasp clear of its
#: neighbours, at their true poses (given to ``Task.scene``, which may want a scene with something to pick)?
Graspable = Callable[[Workcell, int], bool]


class EpisodeFailed(Exception):
    """Ends an episode with the failure ``reason`` (raised by the episode's phases and the tasks' verdicts)."""

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


@dataclass(frozen=True)
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


class Task(Protocol):
    """A trial task (the module docstring says how the pieces fit)."""

    #: The ``--task`` name.
    name: str
    #: The ``Observation.im_id`` of every capture an episode takes (``perception.PICK_LOOK``, ...).
    looks: tuple[int, ...]
    #: Does the task hold the block firmly (``config.FirmHoldConfig``) unless the campaign or its object set
    #: says otherwise (``TrialConfig.firm_hold_tasks``)?
    firm_hold: bool

    @property
    def fixed_looks(self) -> tuple[int, ...]:
        """The looks whose frames do not depend on what the robot did before them: those a ``--captures-only``
        run takes (all of ``looks`` but in a task whose later looks follow its picks)."""
        ...

    def blocks(self, cfg: TrialConfig) -> tuple[int, int]:
        """Fewest and most blocks of an episode's scene (its count is drawn uniformly between them)."""
        ...

    def check(self, cfg: TrialConfig) -> None:
        """A one-line UserError, naming the setting to change, unless the campaign's settings can serve the task
        (kitting needs a block type with an upright face, ...)."""
        ...

    def scene(self, cfg: TrialConfig, seed: int, n_blocks: int, graspable: Graspable) -> Workcell:
        """The episode's settled scene of ``n_blocks`` blocks to pick, drawn from ``seed`` only;
        ``SceneUnsettled`` when no draw settles (recorded as a simulation error)."""
        ...

    def new_record(self, episode: int, seed: int, scene_seed: int, n_blocks: int, perception: str) -> EpisodeRecord:
        """The episode's record, before anything ran."""
        ...

    def run(self, ep: Episode) -> None:
        """The episode after its scene: its phases in order, filling in ``ep.rec``; raises ``EpisodeFailed``."""
        ...

    def metrics(self, records: list[dict]) -> dict:
        """The task's own entries of the campaign summary, over its episodes' JSON records."""
        ...


class PickTask:
    """A task that picks one block and sets it down (a ``Task``): ``run`` is the sequence look and perceive, plan,
    pick, lift and carry to the ``goal``, place, ``judge``; subclasses fill in the hooks."""

    name: str = ""
    looks: tuple[int, ...] = (PICK_LOOK,)
    firm_hold: bool = False
    #: The failure when perception found blocks but ``pickable`` allows none of them.
    unpickable: Failure = Failure.UNREACHABLE

    @property
    def fixed_looks(self) -> tuple[int, ...]:
        """All of ``looks``."""
        return self.looks

    def blocks(self, cfg: TrialConfig) -> tuple[int, int]:
        """``TrialConfig.min_blocks`` and ``max_blocks``."""
        return cfg.min_blocks, cfg.max_blocks

    def check(self, cfg: TrialConfig) -> None:
        """Every campaign's settings can serve the task."""

    def scene(self, cfg: TrialConfig, seed: int, n_blocks: int, graspable: Graspable) -> Workcell:
        raise NotImplementedError

    def new_record(self, episode: int, seed: int, scene_seed: int, n_blocks: int, perception: str) -> EpisodeRecord:
        """A record with the task fields (``record.TASK_FIELDS``)."""
        return EpisodeRecord(episode, seed, scene_seed, n_blocks, perception, task=self.name)

    def metrics(self, records: list[dict]) -> dict:
        """None beyond ``grasping.stats.summarise``'s."""
        return {}

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

    def judge(self, ep: Episode, plan: Plan, context: Any) -> None:
        """After the hand has let go: the verdict, recorded; ``EpisodeFailed`` unless the task succeeded."""
        raise NotImplementedError


def task_types(cfg: TrialConfig) -> list[PartType]:
    """The block types the task's scenes draw from (the scene's ``block_types``, or its whole object set)."""
    cat = load_catalog(cfg.scene.workcell.objects)
    return [cat[n] for n in cfg.scene.block_types if n in cat] if cfg.scene.block_types else list(cat.values())
