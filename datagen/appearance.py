"""Domain randomisation of appearance: block colours and materials, table and floor textures, extra lights.

``sample_appearance`` draws everything from one rng; ``Appearance.add_to(root)`` adds it to a workcell's MJCF before
compiling (composed with ``dm_control.mjcf``); ``light_tint`` recolours the compiled model's lights.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import cv2
import numpy as np
from dm_control import mjcf

from posegrasp.datagen.config import ColourConfig, DatagenConfig, LightConfig, TextureConfig
from posegrasp.datagen.distractors import Distractor, add_distractors, sample_distractors


@dataclass(frozen=True)
class Texture:
    """A procedural 2D texture: ``kind`` (checker, gradient, flat, noise), two colours, speckle fraction,
    repeats per metre and, for ``noise``, the PNG image bytes."""

    kind: str
    rgb1: tuple[float, float, float]
    rgb2: tuple[float, float, float]
    speckle: float
    repeat_per_m: float
    size_px: int
    png: bytes = b""


@dataclass(frozen=True)
class Appearance:
    """Sampled appearance of one scene: per block RGBA and (specular, shininess); table and floor textures;
    the number of extra lights; distractor objects."""

    block_rgba: tuple[tuple[float, float, float, float], ...]
    block_material: tuple[tuple[float, float], ...]
    table: Texture
    floor: Texture
    extra_lights: int
    distractors: tuple[Distractor, ...]

    def add_to(self, root: mjcf.RootElement) -> None:
        """Add textures, block materials (a textured part keeps its texture, with the sampled specular and
        shininess), extra lights and distractors to a workcell MJCF root."""
        for name, tex in (("table", self.table), ("floor", self.floor)):
            geom = root.find("geom", name)
            geom.material = _add_texture_material(root, f"dr_{name}", tex)
            geom.rgba = None  # the material's texture gives the colour
        for k, (rgba, (spec, shin)) in enumerate(zip(self.block_rgba, self.block_material), start=1):
            geom = root.find("geom", f"block_{k}_visual")
            if geom.material is not None:  # a textured part keeps its texture's colours: only the sheen varies
                geom.material.specular, geom.material.shininess = spec, shin
                continue
            mat = root.asset.add("material", name=f"dr_block_{k}", rgba=rgba, specular=spec, shininess=shin)
            geom.material = mat
        for i in range(self.extra_lights):  # placed and dimmed after compiling (sim.scene.randomise_lights)
            root.worldbody.add("light", name=f"dr_light_{i}", pos=(0, 0, 1.5), dir=(0, 0, -1), castshadow=False)
        add_distractors(root, self.distractors)


def jitter_colour(rgb: tuple[float, float, float], cfg: ColourConfig, rng: np.random.Generator) -> tuple[float, float, float]:
    """``rgb`` with its hue shifted by up to ``hue_jitter`` turns and saturation/value scaled by up to +-jitter."""
    h, s, v = colorsys.rgb_to_hsv(*rgb)
    dh, ds, dv = rng.uniform(-1.0, 1.0, 3)
    h = (h + dh * cfg.hue_jitter) % 1.0
    s = float(np.clip(s * (1.0 + ds * cfg.saturation_jitter), 0.0, 1.0))
    v = float(np.clip(v * (1.0 + dv * cfg.value_jitter), 0.02, 1.0))
    return tuple(float(c) for c in colorsys.hsv_to_rgb(h, s, v))


def sample_texture(cfg: TextureConfig, rng: np.random.Generator) -> Texture:
    """A random texture: kind, two random colours, speckle and scale; ``noise`` gets a smooth random image."""
    kind = cfg.kinds[int(rng.integers(len(cfg.kinds)))]
    rgb1, rgb2 = (tuple(float(c) for c in rng.uniform(0.05, 0.95, 3)) for _ in range(2))
    speckle = float(rng.uniform(*cfg.speckle))
    repeat = float(rng.uniform(*cfg.repeat_per_m))
    png = b""
    if kind == "noise":
        n = cfg.size_px
        coarse = rng.random((max(2, n // 8), max(2, n // 8)), dtype=np.float32)
        t = cv2.resize(coarse, (n, n), interpolation=cv2.INTER_CUBIC).clip(0.0, 1.0)[..., None]
        img = (np.asarray(rgb1, np.float32) * (1.0 - t) + np.asarray(rgb2, np.float32) * t) * 255.0
        ok, buf = cv2.imencode(".png", np.round(img).astype(np.uint8)[..., ::-1])
        png = buf.tobytes()
    return Texture(kind, rgb1, rgb2, speckle, repeat, cfg.size_px, png)


def _add_texture_material(root: mjcf.RootElement, name: str, tex: Texture):
    """A 2D texture asset and a material repeating it ``repeat_per_m`` times per metre."""
    if tex.kind == "noise":
        t = root.asset.add("texture", name=name, type="2d", file=mjcf.Asset(tex.png, ".png"))
    else:
        mark = dict(mark="random", random=tex.speckle, markrgb=tex.rgb2) if tex.speckle > 0 else {}
        t = root.asset.add("texture", name=name, type="2d", builtin=tex.kind, rgb1=tex.rgb1, rgb2=tex.rgb2,
                           width=tex.size_px, height=tex.size_px, **mark)
    return root.asset.add("material", name=name, texture=t, texuniform=True,
                          texrepeat=(tex.repeat_per_m, tex.repeat_per_m), specular=0.1, shininess=0.1)


def sample_appearance(cfg: DatagenConfig, n_blocks: int, rng: np.random.Generator) -> Appearance:
    """Draw a scene's appearance: block colours (palette entry + jitter) and materials, textures, lights,
    distractors."""
    c = cfg.colours
    pal = c.palette
    rgba = tuple((*jitter_colour(pal[int(rng.integers(len(pal)))], c, rng), 1.0) for _ in range(n_blocks))
    mats = tuple((float(rng.uniform(*c.specular)), float(rng.uniform(*c.shininess))) for _ in range(n_blocks))
    table, floor = sample_texture(cfg.textures, rng), sample_texture(cfg.textures, rng)
    extra = int(rng.integers(cfg.lights.extra[0], cfg.lights.extra[1] + 1))
    distractors = tuple(sample_distractors(cfg.distractors, cfg.workcell.pick_area, rng))
    return Appearance(rgba, mats, table, floor, extra, distractors)


def light_tint(model, cfg: LightConfig, rng: np.random.Generator) -> None:
    """Scale each light's diffuse colour per channel by 1 +- ``tint`` (after ``randomise_lights``)."""
    model.light_diffuse[:] = np.clip(model.light_diffuse * rng.uniform(1 - cfg.tint, 1 + cfg.tint, (model.nlight, 3)),
                                     0.0, 1.0)
