"""A randomised, settled scene for dataset generation: blocks dropped into the pick area (closer than their
size, so some land on others; ``table``) or parts dropped into a heap (``pile``) or a tote (``bin``:
``sim.clutter``), among randomised looks (textures, materials, lights, distractors), everything drawn from one rng.

Physics runs with MuJoCo's sleeping islands enabled: blocks at rest cost nothing while the arm moves between
viewpoints, and wake up if the arm touches them.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from posegrasp.datagen.appearance import Appearance, light_tint, sample_appearance
from posegrasp.datagen.config import DatagenConfig
from posegrasp.catalog import PartType, load_catalog
from posegrasp.errors import ConfigError
from posegrasp.sim.clutter import build_clutter_scene, check_clutter, clutter_workcell
from posegrasp.sim.scene import SceneConfig, area_capacity, choose_types, drop_and_settle, fitting, randomise_lights
from posegrasp.sim.workcell import BlockInstance, Workcell


@dataclass
class GenScene:
    """A settled generation scene: the workcell (arm at home) and the appearance it was built with."""

    workcell: Workcell
    appearance: Appearance
    drops: int  #: drops of all blocks (table) or waves of parts (pile, bin) it took


def scene_config(cfg: DatagenConfig) -> SceneConfig:
    """The ``sim.scene`` settings matching a generation config."""
    return SceneConfig(block_types=cfg.block_types, palette=cfg.colours.palette, min_spacing=cfg.min_spacing,
                       light_intensity=cfg.lights.intensity, workcell=cfg.workcell)


def check_capacity(cfg: DatagenConfig) -> None:
    """Raise a ConfigError if the largest block count does not fit in the pick area (table) or the tote (pile,
    bin: ``sim.clutter.check_clutter``, which also refuses a tote the hand cannot reach)."""
    if cfg.scene != "table":
        cat = load_catalog(cfg.workcell.objects)
        types = [cat[t] for t in cfg.block_types or cat]
        check_clutter(cfg.workcell, cfg.scene, cfg.clutter, types, cfg.clutter.parts[1])
        return
    cap = area_capacity(scene_config(cfg))
    if cfg.blocks[1] > cap:
        raise ConfigError(f"{cfg.blocks[1]} blocks do not fit in the pick area (at most {cap}); lower --blocks")


def stack_drops(poses: list[np.ndarray], types: list[PartType]) -> list[np.ndarray]:
    """Raise drop poses whose bounding spheres overlap an earlier block's in the plane above it, so blocks
    dropped closer than their size start apart and land on each other (piles) instead of interpenetrating."""
    out: list[np.ndarray] = []
    for T, b in zip(poses, types):
        T = T.copy()
        for U, c in zip(out, types):
            r = 0.5 * (b.diameter + c.diameter)
            if np.linalg.norm(T[:2, 3] - U[:2, 3]) < r:
                T[2, 3] = max(T[2, 3], U[2, 3] + r)
        out.append(T)
    return out


def build_scene(cfg: DatagenConfig, rng: np.random.Generator, max_drops: int = 20) -> GenScene:
    """Draw block count, types and appearance from ``rng``, build the workcell and settle the dropped blocks."""
    scfg = scene_config(cfg)
    counts = cfg.blocks if cfg.scene == "table" else cfg.clutter.parts
    n = int(rng.integers(counts[0], counts[1] + 1))
    types = choose_types(scfg, n, rng)
    if cfg.scene == "table":
        types = fitting(types, scfg)
        n = len(types)
    appearance = sample_appearance(cfg, n, rng)
    parts = [BlockInstance(b, c) for b, c in zip(types, appearance.block_rgba)]
    if cfg.scene == "table":
        wc = Workcell(cfg.workcell, parts, extras=appearance.add_to)
    else:
        wc = clutter_workcell(cfg.workcell, cfg.scene, parts, cfg.clutter, extras=appearance.add_to)
    wc.model.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_SLEEP)
    randomise_lights(wc, scfg, rng)
    light_tint(wc.model, cfg.lights, rng)
    if cfg.scene == "table":
        drops = drop_and_settle(wc, scfg, types, rng, max_drops, margin=cfg.area_margin, arrange=stack_drops)
    else:
        drops = build_clutter_scene(wc, cfg.scene, cfg.clutter, rng).waves
    return GenScene(wc, appearance, drops)
