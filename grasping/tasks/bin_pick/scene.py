"""Bin picking's scene: a settled heap of parts in the tote (``bin``) or on the table (``pile``) with the out-box
beside it, and the heap's area as the planner and the verdicts see it (``Area``, ``wall_points``)."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np
from dm_control import mjcf

from posegrasp.catalog import PartType, catalog_by_id
from posegrasp.errors import ConfigError
from posegrasp.grasping.tasks.bin_pick.config import BinPickConfig
from posegrasp.sim.clutter import build_clutter_scene, clutter_workcell, tote_of
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.scene import choose_types
from posegrasp.sim.tote import Tote
from posegrasp.sim.tray import Tray
from posegrasp.sim.workcell import BlockInstance, Workcell

if TYPE_CHECKING:
    from posegrasp.grasping.config import TrialConfig

#: Model name of the out-box: the prefix of its geoms' names in a workcell.
OUTBOX = "outbox"


def outbox_of(workcell: WorkcellConfig, cfg: BinPickConfig) -> Tote:
    """The out-box of ``cfg``, its centre ``outbox_offset`` from the heap's (the workcell's pick area)."""
    return Tote(cfg.outbox, tuple(float(c) for c in np.add(workcell.pick_area.center, cfg.outbox_offset)))


def check_outbox(workcell: WorkcellConfig, cfg: BinPickConfig) -> None:
    """A one-line ConfigError where the out-box, walls included, overlaps the heap's area: the tote with its walls,
    or a pile's footprint grown by ``pile_margin``."""
    heap, box = tote_of(workcell, cfg.clutter), outbox_of(workcell, cfg)
    grow = heap.cfg.thickness if cfg.scene == "bin" else cfg.clutter.pile_margin
    (a, b), (c, d) = heap.inner_bounds(), box.inner_bounds()
    gap = np.maximum(c[:2] - box.cfg.thickness - b[:2] - grow, a[:2] - grow - d[:2] - box.cfg.thickness)
    if np.all(gap < -1e-9):  # touching is no overlap
        raise ConfigError(f"bin_pick.outbox_offset = {list(cfg.outbox_offset)} m puts the out-box on the "
                          f"{cfg.scene}'s area (overlap {1000 * -float(gap.max()):.1f} mm): move it farther away")


def tray_of(workcell: WorkcellConfig, cfg: BinPickConfig) -> Tray:
    """The tray of ``cfg``, centred on the workcell's place area (plus the tray's offset)."""
    c = np.asarray(workcell.place_area.center) + np.asarray(cfg.tray.offset)
    return Tray(cfg.tray, (float(c[0]), float(c[1])))


def add_outbox(box: Tote) -> Callable[[mjcf.RootElement], None]:
    """``extras(root)`` for a workcell: attach the out-box ``box`` (geoms ``outbox/floor``, ``outbox/wall_x0``, ...)."""

    def add(root: mjcf.RootElement) -> None:
        model = box.mjcf_model()
        model.model = OUTBOX
        root.attach(model).pos = (*box.center, 0.0)

    return add


def bin_workcell(cfg: TrialConfig, parts: list[BlockInstance]) -> Workcell:
    """The campaign's bin or pile workcell with ``parts`` (parked until dropped), the out-box or the tray, and the
    tote's stage where ``shakes`` asks for one."""
    b, wc = cfg.bin_pick, cfg.scene.workcell
    extras = tray_of(wc, b).add_to if b.place == "tray" else add_outbox(outbox_of(wc, b))
    return clutter_workcell(wc, b.scene, parts, b.clutter, extras=extras, shaker=b.shaker if b.shakes else None)


def kit_types(cfg: TrialConfig, n_parts: int, rng: np.random.Generator) -> list[PartType]:
    """The types of ``n_parts`` parts of the tray's kit (slots drawn without replacement), in drawn order."""
    by_name = {t.name: t for t in catalog_by_id(cfg.scene.workcell.objects).values()}
    slots = cfg.bin_pick.tray.slots
    return [by_name[slots[i].type] for i in rng.permutation(len(slots))[:n_parts]]


def bin_scene(cfg: TrialConfig, seed: int, n_parts: int) -> Workcell:
    """A settled heap of ``n_parts`` parts (types and colours drawn from ``seed``; with the tray, of its kit) in the
    tote or on the table."""
    rng = np.random.default_rng(seed)
    types = kit_types(cfg, n_parts, rng) if cfg.bin_pick.place == "tray" else choose_types(cfg.scene, n_parts, rng)
    colours = [cfg.scene.palette[i] for i in rng.integers(0, len(cfg.scene.palette), size=n_parts)]
    wc = bin_workcell(cfg, [BlockInstance(t, (*c, 1.0)) for t, c in zip(types, colours)])
    build_clutter_scene(wc, cfg.bin_pick.scene, cfg.bin_pick.clutter, rng)
    return wc



@dataclass(frozen=True)
class Area:
    """Where the heap lies: the tote (``walls``) or, for a pile, its footprint grown by the pile margin; ``floor``
    and ``top`` are the heights (m) of its floor and of its walls' top (the floor for a pile)."""

    tote: Tote
    walls: bool
    margin: float

    @property
    def floor(self) -> float:
        return self.tote.floor_z if self.walls else 0.0

    @property
    def top(self) -> float:
        return self.tote.top_z if self.walls else 0.0

    def holds(self, xy: np.ndarray, inset: float = 0.0) -> np.ndarray:
        """Per world point (N, 2 or more): does its xy lie in the area, ``inset`` (m) in from its edges?"""
        lo, hi = self.tote.inner_bounds()
        grow = self.margin - inset
        p = np.asarray(xy, float).reshape(-1, np.shape(xy)[-1])[:, :2]
        return np.all((p >= lo[:2] - grow) & (p <= hi[:2] + grow), axis=1)


def area_of(wc: Workcell, b: BinPickConfig) -> Area:
    """The heap's area in the workcell ``wc``."""
    walls = b.scene == "bin"
    return Area(tote_of(wc.cfg, b.clutter), walls, 0.0 if walls else b.clutter.pile_margin)


@functools.lru_cache(maxsize=8)
def wall_points(tote: Tote, spacing: float = 0.005) -> np.ndarray:
    """(N, 3) world points (m) every ``spacing`` on the tote walls' inner faces and on their top rims."""
    lo, hi = tote.inner_bounds()
    t = tote.cfg.thickness
    pts = []
    zs = np.arange(lo[2], hi[2] + 1e-9, spacing)
    for axis in (0, 1):
        other = 1 - axis
        s = np.arange(lo[other] - t, hi[other] + t + 1e-9, spacing)
        for side, inward in ((lo[axis], -1.0), (hi[axis], 1.0)):
            for off in np.arange(0.0, t + 1e-9, spacing):  # the inner face, then across the rim
                for z in (zs if off == 0.0 else [hi[2]]):
                    p = np.zeros((len(s), 3))
                    p[:, axis], p[:, other], p[:, 2] = side + inward * off, s, z
                    pts.append(p)
    return np.concatenate(pts)
