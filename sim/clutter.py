"""Clutter scenes: parts dropped from random poses into a heap and settled by physics, in the tote (``bin``) or on
the table where the tote would stand (``pile``: the same heap without walls).

``clutter_workcell`` composes the workcell with the parts (and, for a bin, the tote: ``sim.tote``);
``build_clutter_scene`` drops and settles them, the same scene for the same seed, settings and MuJoCo version;
``check_clutter`` refuses, with one line, part counts that cannot fit and totes the hand cannot reach.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Callable, Sequence

import mujoco
import numpy as np
from dm_control import mjcf

from posegrasp.catalog import PartType
from posegrasp.config import settings, within
from posegrasp.errors import SceneUnsettled, UserError
from posegrasp.geometry import make_T, transform_points
from posegrasp.sim.config import WorkcellConfig, check_pairs
from posegrasp.sim.scene import SETTLE_PERIOD, random_rotation, run_held
from posegrasp.sim.shaker import ShakerConfig
from posegrasp.sim.tote import Tote, ToteConfig, check_reach, tote_geoms
from posegrasp.sim.workcell import PARKING_GAP, PARKING_Y, BlockInstance, Workcell

CLUTTER_KINDS = ("pile", "bin")


@settings
class ClutterConfig:
    """Pile and bin scenes: how many parts, the tote, how the parts are dropped and when they count as settled."""

    #: Parts per scene, drawn uniformly in [min, max].
    parts: tuple[int, int] = field(default=(12, 12), metadata=within(1, 10_000))
    #: Most parts a scene may hold.
    max_parts: int = field(default=30, metadata=within(1, 200))
    #: Largest share of the tote's inner volume the parts' bounding boxes may fill (the largest type counted for every
    #: part).
    max_fill: float = field(default=0.6, metadata=within(0.01, 2.0))
    #: The tote of bin scenes; a pile is dropped onto its footprint.
    tote: ToteConfig = field(default_factory=ToteConfig)
    #: Height (m) of the lowest drop point of a part's bounding sphere above the tote's walls.
    drop_height: float = field(default=0.02, metadata=within(0.0, 1.0))
    #: A pile's parts must rest with their centres within this distance (m) of the tote's footprint.
    pile_margin: float = field(default=0.05, metadata=within(0.0, 1.0))
    #: A heap has settled once no part has moved farther (m) or turned more (deg) than this ...
    rest_motion: tuple[float, float] = (0.002, 2.0)
    #: ... over the last this long (s) ...
    rest_time: float = field(default=0.2, metadata=within(0.02, 10.0))
    #: ... within this simulated time (s) after the drop.
    settle_timeout: float = field(default=6.0, metadata=within(0.1, 120.0))
    #: Parts dropped at once; each wave settles before the next lands on it.
    wave_size: int = field(default=12, metadata=within(1, 200))
    #: Extra waves that drop again the parts that came to rest out of place.
    max_redrops: int = field(default=4, metadata=within(0, 100))
    #: Drops of the whole scene, from the same generator, before it counts as unsettled: a wave that never settles
    #: (a cylinder on its side rolls on: the contacts have no rolling resistance) starts the scene again.
    draws: int = field(default=5, metadata=within(1, 100))

    def __post_init__(self) -> None:
        check_pairs(self, "parts")


@dataclass(frozen=True)
class SettledClutter:
    """A settled clutter scene: each part with its resting pose ``T_world_obj`` (m), in the workcell's block order;
    the waves it was dropped in and the simulated time (s) they took to settle, all together."""

    parts: list[tuple[PartType, np.ndarray]]
    waves: int
    settle_time: float


def tote_of(workcell: WorkcellConfig, cfg: ClutterConfig) -> Tote:
    """The tote of ``cfg`` centred on the workcell's pick area (a pile's footprint)."""
    return Tote.in_pick_area(workcell, cfg.tote)


def check_clutter(workcell: WorkcellConfig, kind: str, cfg: ClutterConfig, types: Sequence[PartType],
                  n_parts: int) -> None:
    """Raise a one-line UserError for an unknown ``kind``, more than ``max_parts`` parts, parts of ``types`` that
    could not fit (a part wider than the tote's floor; ``n_parts`` of the largest type's bounding box filling more
    than ``max_fill`` of the tote) or, for a bin, a tote the hand cannot reach (``sim.tote.check_reach``)."""
    if kind not in CLUTTER_KINDS:
        raise UserError(f"clutter scene {kind!r} must be one of {', '.join(CLUTTER_KINDS)}")
    if n_parts > cfg.max_parts:
        raise UserError(f"{n_parts} parts are more than a {kind} scene holds (max_parts {cfg.max_parts}); use fewer")
    tote = tote_of(workcell, cfg)
    widest = max(types, key=lambda t: t.diameter)
    if widest.diameter > min(cfg.tote.inner_size):
        raise UserError(f"part {widest.name!r} ({widest.diameter:.3f} m across) does not fit the tote's floor "
                        f"{list(cfg.tote.inner_size)} m; use a larger tote or other parts")
    largest = max(types, key=lambda t: float(np.prod(t.extents)))
    fill = n_parts * float(np.prod(largest.extents)) / tote.inner_volume()
    if fill > cfg.max_fill:
        cap = int(cfg.max_fill * tote.inner_volume() / float(np.prod(largest.extents)))
        raise UserError(f"{n_parts} parts do not fit the tote (up to {n_parts} x {largest.name!r} would fill "
                        f"{fill:.0%} of it, max_fill {cfg.max_fill:.0%}); use {cap} parts or fewer or a larger tote")
    if kind == "bin":
        check_reach(workcell, tote)


def clutter_workcell(workcell: WorkcellConfig, kind: str, parts: Sequence[BlockInstance], cfg: ClutterConfig,
                     extras: Callable[[mjcf.RootElement], None] | None = None,
                     shaker: ShakerConfig | None = None) -> Workcell:
    """The workcell with ``parts`` (parked until dropped) and, for a ``bin``, the tote in the pick area (on a
    ``shaker`` stage if given: ``sim.shaker``); ``extras(root)`` as in ``Workcell``."""
    if kind not in CLUTTER_KINDS:
        raise ValueError(f"clutter scene {kind!r} must be one of {', '.join(CLUTTER_KINDS)}")
    tote = tote_of(workcell, cfg) if kind == "bin" else None

    def compose(root: mjcf.RootElement) -> None:
        if extras is not None:
            extras(root)
        if tote is not None:
            tote.add_to(root, shaker)

    return Workcell(workcell, parts, extras=compose)


#: Drop points drawn per part; the part is dropped from the one where it starts lowest (a compact heap, short falls).
DROP_CANDIDATES = 8


def _clear_height(c: np.ndarray, r: float, centres: list[np.ndarray], radii: list[float]) -> float:
    """Lowest height >= ``c[2]`` at which a sphere of radius ``r`` centred above ``c[:2]`` clears every sphere
    (``centres``, ``radii``): each raise lifts it past one more sphere, so it ends after at most len(centres)
    passes."""
    c = c.copy()
    moved = True
    while moved:
        moved = False
        for cj, rj in zip(centres, radii):
            gap2 = (r + rj) ** 2 - float(np.sum((c[:2] - cj[:2]) ** 2))
            if gap2 > 0 and float(np.sum((c - cj) ** 2)) < (r + rj) ** 2 - 1e-12:
                c[2] = cj[2] + np.sqrt(gap2) + 1e-6
                moved = True
    return float(c[2])


def clutter_drop_poses(tote: Tote, cfg: ClutterConfig, types: Sequence[PartType], rng: np.random.Generator,
                       floor: float | None = None) -> list[np.ndarray]:
    """World drop poses: random orientations; per part, the lowest start of ``DROP_CANDIDATES`` centres drawn
    uniformly over the tote's floor (its bounding sphere, radius r, over the floor where the floor is wide
    enough), the sphere ``drop_height`` above ``floor`` (m; default the walls' top) or, where earlier
    parts' spheres are in the way, just clear of them."""
    lo, hi = tote.inner_bounds()
    base = max(hi[2], floor if floor is not None else hi[2]) + cfg.drop_height
    centres: list[np.ndarray] = []
    radii: list[float] = []
    poses = []
    for t in types:
        r = 0.5 * t.diameter
        half = np.maximum(0.5 * (hi[:2] - lo[:2]) - r, 0.0)  # the whole sphere over the floor, where it is wide enough
        xy = rng.uniform(tote.center - half, tote.center + half, size=(DROP_CANDIDATES, 2))
        starts = [np.array([x, y, base + r]) for x, y in xy]
        z = [_clear_height(c, r, centres, radii) for c in starts]
        c = starts[int(np.argmin(z))]
        c[2] = min(z)
        centres.append(c)
        radii.append(r)
        poses.append(make_T(random_rotation(rng), c))
    return poses


def in_place(workcell: Workcell, kind: str, cfg: ClutterConfig, tol: float = 0.002) -> np.ndarray:
    """Per part: is it in place? A bin's part lies entirely between the tote's inner walls and above its floor
    (every vertex, within ``tol`` m); a pile's centre lies within ``pile_margin`` of the tote's footprint."""
    tote = tote_of(workcell.cfg, cfg)
    poses = workcell.block_poses()
    if kind == "bin":
        return np.array([tote.contains(transform_points(T, b.block.vertices), tol)
                         for T, b in zip(poses, workcell.blocks)])
    lo, hi = tote.inner_bounds()
    xy = poses[:, :2, 3]
    return np.all((xy >= lo[:2] - cfg.pile_margin) & (xy <= hi[:2] + cfg.pile_margin), axis=1)


def park(workcell: Workcell, k: int) -> None:
    """Part ``k`` (1-based) back at its parking spot, away from everything, floating (gravity compensated)."""
    workcell.set_block_pose(k, make_T(np.eye(3), (0.0, PARKING_Y + PARKING_GAP * k, 0.5)))
    workcell.model.body_gravcomp[workcell.block_body[k - 1]] = 1.0


def _heap_top(workcell: Workcell, dropped: Sequence[int]) -> float | None:
    """Height (m) of the highest vertex of parts ``dropped`` (1-based), None for none."""
    if not dropped:
        return None
    poses = workcell.block_poses()
    return max(float(transform_points(poses[k - 1], workcell.blocks[k - 1].block.vertices)[:, 2].max())
               for k in dropped)


def settle_heap(workcell: Workcell, cfg: ClutterConfig) -> bool:
    """Step physics, the arm held still (``sim.scene.run_held``), until no part has moved more than
    ``rest_motion`` (m, deg) from where it was ``rest_time`` ago, at any control period in between; False after
    ``settle_timeout`` simulated seconds. Net motion, not speed: a heap's contacts keep parts trembling (and
    creeping by a few mm/s) in place long after it has come to rest."""
    window = max(1, round(cfg.rest_time / SETTLE_PERIOD))
    history: deque[np.ndarray] = deque(maxlen=window + 1)
    max_move, max_turn = cfg.rest_motion[0], np.deg2rad(cfg.rest_motion[1])

    def done() -> bool:
        history.append(workcell.block_poses())
        if len(history) <= window:
            return False
        P0 = history[0]
        for P in list(history)[1:]:
            move = np.linalg.norm(P[:, :3, 3] - P0[:, :3, 3], axis=1)
            cos = 0.5 * (np.einsum("kij,kij->k", P0[:, :3, :3], P[:, :3, :3]) - 1.0)  # trace(R0^T R) = 1 + 2 cos
            if move.max() >= max_move or np.arccos(np.clip(cos, -1.0, 1.0)).max() >= max_turn:
                return False
        return True

    return run_held(workcell, cfg.settle_timeout, done)


def build_clutter_scene(workcell: Workcell, kind: str, cfg: ClutterConfig,
                        seed: int | np.random.Generator) -> SettledClutter:
    """Drop the workcell's parts (its blocks), in waves of ``wave_size``, from random poses above the tote
    (``clutter_drop_poses``, above the heap so far), and let physics settle each wave with the arm held still.

    Each wave must settle (``settle_heap``) within ``settle_timeout`` of its drop. Parts that come to rest out of
    place (``in_place``: over or outside the walls, pushed there by a later wave too) go back and drop again in a
    later wave, ``max_redrops`` such waves at most; a wave that does not settle, or parts still out of place
    then, start the scene again (the generator drawn on), ``draws`` times at most before SceneUnsettled.

    ``workcell`` comes from ``clutter_workcell(…, kind, …)`` (a bin's has the tote). The scene is the same for the
    same ``seed`` (or generator state), settings and MuJoCo version; velocities and time are zeroed at the end.
    """
    if (kind == "bin") != bool(tote_geoms(workcell.model).size):
        raise ValueError(f"a {kind} scene needs a workcell from clutter_workcell(..., {kind!r}, ...)")
    rng = np.random.default_rng(seed)
    for draw in range(cfg.draws):
        try:
            waves, sim_time = _drop_waves(workcell, kind, cfg, rng)
            break
        except SceneUnsettled as e:
            if draw == cfg.draws - 1:
                raise SceneUnsettled(f"{e} (the last of {cfg.draws} draws of the scene)") from None
    workcell.data.qvel[:] = 0.0
    workcell.data.time = 0.0
    return SettledClutter(list(zip([b.block for b in workcell.blocks], workcell.block_poses())), waves, sim_time)


def _drop_waves(workcell: Workcell, kind: str, cfg: ClutterConfig, rng: np.random.Generator) -> tuple[int, float]:
    """One draw of ``build_clutter_scene``: every part parked, then dropped in waves; the waves and their simulated
    settling time (s); SceneUnsettled when a wave does not settle or parts stay out of place."""
    tote = tote_of(workcell.cfg, cfg)
    n = len(workcell.blocks)
    workcell.reset(workcell.arm_q)
    for k in range(1, n + 1):
        park(workcell, k)
    pending, waves, sim_time = list(range(1, n + 1)), 0, 0.0
    max_waves = -(-n // cfg.wave_size) + cfg.max_redrops
    while pending and waves < max_waves:
        waves += 1
        wave, pending = pending[:cfg.wave_size], pending[cfg.wave_size:]
        dropped = [k for k in range(1, n + 1) if k not in wave and k not in pending]
        poses = clutter_drop_poses(tote, cfg, [workcell.blocks[k - 1].block for k in wave], rng,
                                   _heap_top(workcell, dropped))
        for k, T in zip(wave, poses):
            workcell.set_block_pose(k, T)
            workcell.model.body_gravcomp[workcell.block_body[k - 1]] = 0.0
        mujoco.mj_forward(workcell.model, workcell.data)
        t0 = workcell.data.time
        if not settle_heap(workcell, cfg):
            raise SceneUnsettled(f"a {kind} scene's parts did not come to rest within {cfg.settle_timeout} s of a "
                               f"drop (at rest: moving less than {cfg.rest_motion[0]} m and {cfg.rest_motion[1]} deg "
                               f"in {cfg.rest_time} s); use fewer parts or a longer settle_timeout")
        sim_time += workcell.data.time - t0
        out = [k for k, ok in zip(range(1, n + 1), in_place(workcell, kind, cfg)) if not ok and k not in pending]
        for k in out:
            park(workcell, k)
        pending = out + pending
    if pending:
        raise SceneUnsettled(f"{len(pending)} of the {n} parts of a {kind} scene still came to rest out of place "
                           f"after {waves} waves; use fewer parts or a larger tote")
    return waves, sim_time
