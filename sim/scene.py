"""Randomised scenes by seed: blocks dropped into the pick area and settled by simulation.

``make_scene(seed, n_blocks)`` always gives the same scene for the same seed, settings and MuJoCo version.
"""

from __future__ import annotations

from dataclasses import field
from typing import Callable

import mujoco
import numpy as np

from posegrasp.catalog import PartType, load_catalog, set_root
from posegrasp.config import settings
from posegrasp.errors import ConfigError, SceneUnsettled, UserError
from posegrasp.geometry import make_T, quat_to_R
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.workcell import BlockInstance, Workcell

#: Block colours (RGB): saturated toy colours and dull, nearly textureless greys and browns.
PALETTE: tuple[tuple[float, float, float], ...] = (
    (0.80, 0.10, 0.10), (0.10, 0.35, 0.80), (0.95, 0.75, 0.10), (0.10, 0.60, 0.25),
    (0.95, 0.45, 0.05), (0.55, 0.20, 0.65), (0.92, 0.92, 0.90), (0.15, 0.15, 0.17),
    (0.55, 0.55, 0.55), (0.45, 0.33, 0.22), (0.70, 0.62, 0.50), (0.30, 0.70, 0.80),
)


@settings
class SceneConfig:
    """How scenes are randomised. ``block_types`` empty means every catalogue type."""

    #: Object types (names in the object set) a scene draws from; empty: all.
    block_types: tuple[str, ...] = ()
    #: Block colours, RGB in [0, 1].
    palette: tuple[tuple[float, float, float], ...] = PALETTE
    #: Least distance (m) between drop positions in the plane.
    min_spacing: float = 0.055
    #: Height (m) of a block's lowest point above the table when dropped.
    drop_height: float = 0.03
    #: Simulated time (s) allowed for the dropped blocks to come to rest.
    settle_timeout: float = 4.0
    #: Blocks are at rest below these speeds (m/s, rad/s).
    rest_speed: tuple[float, float] = (0.003, 0.1)
    #: Range of the lights' diffuse intensity.
    light_intensity: tuple[float, float] = (0.35, 0.8)
    #: The workcell the scene is built in.
    workcell: WorkcellConfig = field(default_factory=WorkcellConfig)


def area_capacity(cfg: SceneConfig) -> int:
    """How many blocks fit in the pick area at ``min_spacing`` (a hexagonal packing bound)."""
    hx, hy = cfg.workcell.pick_area.half_size
    s = cfg.min_spacing
    return int((2 * hx // s + 1) * (2 * hy // (s * np.sqrt(3) / 2) + 1) * 0.5)


#: Most of the pick area the parts of one scene may cover, each lying on its largest face (the product of its two
#: largest extents): more do not settle apart inside it, so a scene drops the parts drawn past this share.
AREA_FILL = 0.5


def fitting(types: list[PartType], cfg: SceneConfig) -> list[PartType]:
    """The leading ``types`` whose footprints (two largest extents' product, m^2) cover at most ``AREA_FILL`` of the
    pick area; at least the first. The shipped blocks never reach it; large imported parts (a cereal box) do."""
    hx, hy = cfg.workcell.pick_area.half_size
    room, out = AREA_FILL * 4 * hx * hy, []
    for t in types:
        e = np.sort(np.asarray(t.extents))
        room -= e[1] * e[2]
        if out and room < 0:
            break
        out.append(t)
    return out


def check_block_types(names: tuple[str, ...] | list[str], objects: str = "") -> None:
    """Raise a ConfigError naming the ``names`` that are not object types of the set ``objects``."""
    cat = load_catalog(objects)
    unknown = [t for t in names if t not in cat]
    if unknown:
        raise ConfigError(f"unknown block type(s) {unknown}; the object set {set_root(objects).name} has: "
                          f"{', '.join(cat)}")


def choose_types(cfg: SceneConfig, n: int, rng: np.random.Generator) -> list[PartType]:
    """``n`` object types drawn from ``cfg.block_types`` (all of the workcell's object set when empty)."""
    cat = load_catalog(cfg.workcell.objects)
    names = list(cfg.block_types) or list(cat)
    check_block_types(names, cfg.workcell.objects)
    return [cat[names[i]] for i in rng.integers(0, len(names), size=n)]


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation matrix drawn uniformly (a normalised Gaussian quaternion)."""
    q = rng.normal(size=4)
    return quat_to_R(q / np.linalg.norm(q))


class Scene:
    """A settled scene: the workcell with its blocks at rest in the pick area."""

    def __init__(self, workcell: Workcell, seed: int, cfg: SceneConfig):
        self.workcell = workcell
        self.seed = seed
        self.cfg = cfg

    @property
    def blocks(self) -> list[BlockInstance]:
        return self.workcell.blocks

    def in_pick_area(self, margin: float = 0.0) -> np.ndarray:
        """Per block: is its centre inside the pick area (grown by ``margin`` m)?"""
        a = self.cfg.workcell.pick_area
        xy = self.workcell.block_poses()[:, :2, 3]
        return np.all(np.abs(xy - a.center) <= np.add(a.half_size, margin), axis=1)


def drop_poses(cfg: SceneConfig, blocks: list[PartType], rng: np.random.Generator) -> list[np.ndarray]:
    """Poses above the pick area, random orientation, at least ``min_spacing`` apart in the plane."""
    a = cfg.workcell.pick_area
    placed: list[np.ndarray] = []
    poses = []
    for b in blocks:
        r = 0.5 * b.diameter
        lo = np.subtract(a.center, a.half_size) + 0.5 * r
        hi = np.add(a.center, a.half_size) - 0.5 * r
        for _ in range(1000):
            xy = rng.uniform(lo, hi)
            if all(np.linalg.norm(xy - p) >= cfg.min_spacing for p in placed):
                break
        else:
            raise UserError(f"could not place {len(blocks)} blocks in the pick area; use fewer blocks "
                            f"(at most about {area_capacity(cfg)}) or a smaller min_spacing")
        placed.append(xy)
        R = random_rotation(rng)
        poses.append(make_T(R, (xy[0], xy[1], cfg.drop_height + r)))
    return poses


#: Control period (s) of ``run_held``: the arm's hold command is renewed and ``done`` asked this often.
SETTLE_PERIOD = 0.02


def run_held(workcell: Workcell, timeout: float, done: Callable[[], bool]) -> bool:
    """Step physics in control periods of ``SETTLE_PERIOD`` s, the arm held at its pose, thin parts falling no
    faster than their contacts hold (``Workcell.cap_thin_speeds``), until ``done()`` (asked after each period) is
    true; False after ``timeout`` simulated seconds."""
    m = workcell.model
    hold = workcell.arm_q
    steps = max(1, round(SETTLE_PERIOD / m.opt.timestep))
    for _ in range(int(timeout / SETTLE_PERIOD)):
        workcell.command_arm(4.0 * (hold - workcell.arm_q) + workcell.gravity_feedforward())
        workcell.step(steps)
        workcell.cap_thin_speeds()
        if done():
            return True
    return False


def settle(workcell: Workcell, cfg: SceneConfig) -> bool:
    """Step physics with the arm held in place until every block is at rest (slower than ``rest_speed`` for 10
    control periods in a row); False on timeout."""
    rest_for = 0

    def done() -> bool:
        nonlocal rest_for
        v = workcell.block_speeds()
        rest_for = rest_for + 1 if np.all(v[:, 0] < cfg.rest_speed[0]) and np.all(v[:, 1] < cfg.rest_speed[1]) else 0
        return rest_for >= 10

    return run_held(workcell, cfg.settle_timeout, done)


def randomise_lights(workcell: Workcell, cfg: SceneConfig, rng: np.random.Generator) -> None:
    """Light positions, directions (toward the pick area) and intensities from ``rng``."""
    m = workcell.model
    c = np.array([*cfg.workcell.pick_area.center, 0.0])
    for i in range(m.nlight):
        pos = c + np.array([rng.uniform(-0.8, 0.8), rng.uniform(-0.8, 0.8), rng.uniform(0.8, 1.6)])
        m.light_pos[i] = pos
        m.light_dir[i] = (c - pos) / np.linalg.norm(c - pos)
        m.light_diffuse[i] = rng.uniform(*cfg.light_intensity) * np.ones(3) * rng.uniform(0.9, 1.0, 3)
    m.vis.headlight.ambient[:] = rng.uniform(0.15, 0.35)
    m.vis.headlight.diffuse[:] = rng.uniform(0.2, 0.45)


def drop_and_settle(workcell: Workcell, cfg: SceneConfig, types: list[PartType], rng: np.random.Generator,
                    max_drops: int = 20, margin: float = 0.0,
                    arrange: Callable[[list[np.ndarray], list[PartType]], list[np.ndarray]] | None = None) -> int:
    """Drop every block (poses from ``rng``, optionally rearranged by ``arrange``) and settle, until all rest
    inside the pick area grown by ``margin`` m; returns the number of drops used, raises after ``max_drops``."""
    scene = Scene(workcell, 0, cfg)
    for drop in range(1, max_drops + 1):
        workcell.reset()
        poses = drop_poses(cfg, types, rng)
        for k, T in enumerate(arrange(poses, types) if arrange else poses, start=1):
            workcell.set_block_pose(k, T)
        mujoco.mj_forward(workcell.model, workcell.data)
        if settle(workcell, cfg) and scene.in_pick_area(margin).all():
            workcell.data.qvel[:] = 0.0
            workcell.data.time = 0.0
            return drop
    raise SceneUnsettled(f"blocks did not come to rest inside the pick area after {max_drops} drops; "
                         "use fewer blocks or a larger pick area")


def make_scene(seed: int, n_blocks: int, cfg: SceneConfig | None = None, max_drops: int = 20) -> Scene:
    """Build and settle a random scene of ``n_blocks`` blocks (fewer where large parts would crowd the pick area:
    ``fitting``); the arm starts at home.

    If a block ends outside the pick area, all blocks are dropped again (same rng stream), up to ``max_drops``.
    """
    cfg = cfg or SceneConfig()
    if not isinstance(n_blocks, (int, np.integer)) or n_blocks < 1:
        raise UserError(f"number of blocks must be a positive integer, got {n_blocks!r}")
    cap = area_capacity(cfg)
    if n_blocks > cap:
        raise UserError(f"{n_blocks} blocks do not fit in the pick area (at most {cap}); use --blocks {cap} or fewer")
    rng = np.random.default_rng(seed)
    types = choose_types(cfg, n_blocks, rng)
    colours = [cfg.palette[i] for i in rng.integers(0, len(cfg.palette), size=n_blocks)]
    types = fitting(types, cfg)
    wc = Workcell(cfg.workcell, [BlockInstance(b, (*c, 1.0)) for b, c in zip(types, colours)])
    randomise_lights(wc, cfg, rng)
    drop_and_settle(wc, cfg, types, rng, max_drops)
    return Scene(wc, seed, cfg)
