"""Settings of synthetic dataset generation: scene contents, viewpoints, domain randomisation, sensor noise.

Lengths in metres, angles in degrees where the name says ``_deg``, colours RGB in [0, 1]. Every field has a
default; a TOML file of the same layout (tables ``[views]``, ``[colours]``, ``[textures]``, ``[lights]``,
``[distractors]``, ``[depth_noise]``, ``[rgb_noise]``, ``[workcell]``) overrides any of them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from posegrasp.config import load_toml
from posegrasp.errors import ConfigError
from posegrasp.sim.clutter import CLUTTER_KINDS, ClutterConfig
from posegrasp.sim.config import WorkcellConfig, with_objects
from posegrasp.sim.scene import PALETTE, check_block_types


@dataclass(frozen=True)
class ViewConfig:
    """Hand-camera viewpoints on a spherical cap over the clutter, reached by the arm.

    The camera sits ``distance`` from a look-at point among the blocks, ``elevation_deg`` above the table
    plane, at ``azimuth_deg`` about the vertical through the look-at point (0 = on the side of the arm base),
    looking at the point with image-up toward world-up, then rolled by up to ``roll_deg`` about its axis.
    A view whose IK residual exceeds ``max_pos_residual`` (m) or ``max_rot_residual_deg`` is unreachable;
    camera positions farther than ``max_reach`` (m) from the shoulder joint are rejected without IK.
    """

    distance: tuple[float, float] = (0.25, 0.75)
    elevation_deg: tuple[float, float] = (30.0, 88.0)
    azimuth_deg: tuple[float, float] = (-180.0, 180.0)
    roll_deg: float = 60.0
    target_jitter: float = 0.02
    max_pos_residual: float = 0.005
    max_rot_residual_deg: float = 1.0
    max_reach: float = 0.66
    ik_iters: int = 60
    attempts_per_view: int = 4
    drive_gain: float = 10.0
    drive_tol: float = 0.005
    drive_timeout: float = 6.0


@dataclass(frozen=True)
class ColourConfig:
    """Block colours: a palette entry (saturated toy colours and dull, nearly textureless greys and browns)
    with hue (fraction of a turn), saturation and value jitter; material specular and shininess ranges."""

    palette: tuple[tuple[float, float, float], ...] = PALETTE
    hue_jitter: float = 0.03
    saturation_jitter: float = 0.15
    value_jitter: float = 0.2
    specular: tuple[float, float] = (0.05, 0.6)
    shininess: tuple[float, float] = (0.05, 0.7)


@dataclass(frozen=True)
class TextureConfig:
    """Procedural table and floor textures: MuJoCo builtins (``checker``, ``gradient``, ``flat``) or a small
    generated ``noise`` image, random colours, ``speckle`` fraction of random marks, repeats per metre."""

    kinds: tuple[str, ...] = ("checker", "gradient", "flat", "noise")
    speckle: tuple[float, float] = (0.0, 0.05)
    repeat_per_m: tuple[float, float] = (1.0, 12.0)
    size_px: int = 64


@dataclass(frozen=True)
class LightConfig:
    """Lights: ``extra`` added to the workcell's two, then all placed, aimed and dimmed at random
    (``intensity`` diffuse range, per-channel ``tint``)."""

    extra: tuple[int, int] = (0, 3)
    intensity: tuple[float, float] = (0.3, 0.8)
    tint: float = 0.15


@dataclass(frozen=True)
class DistractorConfig:
    """Unlabelled primitives (box, cylinder, sphere, capsule) resting on the table in a ``band`` (m) around
    the pick area: they occlude blocks from oblique views. ``size`` is the half-extent range (m)."""

    count: tuple[int, int] = (0, 4)
    size: tuple[float, float] = (0.01, 0.045)
    band: tuple[float, float] = (0.05, 0.15)


@dataclass(frozen=True)
class DepthNoiseConfig:
    """Structured-light depth sensor model.

    Projector shadows and dropout at depth edges, lateral jitter (``pixel_shift`` px), axial noise
    ``sigma = sigma_base + sigma_quad (z - z_ref)^2 + sigma_angle / sqrt(z) theta^2 / (pi/2 - theta)^2``,
    disparity quantisation (``baseline`` m, ``disparity_step`` px) and random dropout.
    ``keep_clean`` also writes the noiseless depth to ``depth_clean/``.
    """

    enabled: bool = True
    sigma_base: float = 0.0008
    sigma_quad: float = 0.0019
    z_ref: float = 0.4
    sigma_angle: float = 0.0001
    pixel_shift: float = 0.25
    baseline: float = 0.05
    disparity_step: float = 0.125
    edge_threshold: float = 0.01
    edge_dropout: float = 0.5
    random_dropout: float = 0.002
    keep_clean: bool = False


@dataclass(frozen=True)
class RgbNoiseConfig:
    """Camera effects on the colour image: exposure gain and gamma, Gaussian blur (probability, sigma px)
    and Gaussian sensor noise (std in grey levels)."""

    enabled: bool = True
    gain: tuple[float, float] = (0.75, 1.25)
    gamma: tuple[float, float] = (0.85, 1.15)
    blur_prob: float = 0.3
    blur_sigma: tuple[float, float] = (0.3, 1.2)
    noise_std: tuple[float, float] = (0.0, 4.0)


@dataclass(frozen=True)
class DatagenConfig:
    """Everything that decides the content of a generated dataset (besides seed, scene and view counts).

    ``blocks``: blocks per scene, drawn uniformly in [min, max]; ``block_types``: names in the object set (empty: all);
    ``min_spacing``: least distance (m) between drop points in the plane (smaller: piles, more occlusion);
    blocks must come to rest within ``area_margin`` (m) of the pick area, else they are dropped again.
    ``depth_scale``: BOP depth png units (value x depth_scale = mm). ``rgb_format``: ``jpg``, ``png`` or
    ``auto`` (jpg for ``train_pbr``, png otherwise, as in the BOP datasets). ``msaa``: multisamples per pixel
    of the colour image (anti-aliasing; 0 renders it faster with jagged edges).
    """

    blocks: tuple[int, int] = (3, 8)
    block_types: tuple[str, ...] = ()
    min_spacing: float = 0.03
    area_margin: float = 0.04
    depth_scale: float = 0.1
    rgb_format: str = "auto"
    jpg_quality: int = 95
    msaa: int = 4
    views: ViewConfig = field(default_factory=ViewConfig)
    colours: ColourConfig = field(default_factory=ColourConfig)
    textures: TextureConfig = field(default_factory=TextureConfig)
    lights: LightConfig = field(default_factory=LightConfig)
    distractors: DistractorConfig = field(default_factory=DistractorConfig)
    depth_noise: DepthNoiseConfig = field(default_factory=DepthNoiseConfig)
    rgb_noise: RgbNoiseConfig = field(default_factory=RgbNoiseConfig)
    workcell: WorkcellConfig = field(default_factory=WorkcellConfig)
    #: Scene kind (``--scene``): ``table`` (blocks dropped apart over the pick area), ``pile`` (parts dropped into
    #: a heap) or ``bin`` (the heap in a tote).
    scene: str = "table"
    #: Pile and bin scenes: parts per scene (``--blocks``; ``blocks`` is the table's), tote, drop and settling.
    clutter: ClutterConfig = field(default_factory=ClutterConfig)
    #: Viewpoints of pile and bin scenes: closer and steeper than the table's, to look into the tote.
    clutter_views: ViewConfig = field(default_factory=lambda: ViewConfig(distance=(0.3, 0.6),
                                                                          elevation_deg=(45.0, 88.0)))


SCENES = ("table", *CLUTTER_KINDS)
TEXTURE_KINDS = ("checker", "gradient", "flat", "noise")
RGB_FORMATS = ("auto", "jpg", "png")


def _check_range(name: str, r: tuple, lo: float | None = None) -> None:
    if len(r) != 2 or r[0] > r[1]:
        raise ConfigError(f"{name} must be a [min, max] pair with min <= max, got {list(r)}")
    if lo is not None and r[0] < lo:
        raise ConfigError(f"{name} must be >= {lo}, got {list(r)}")


def validate(cfg: DatagenConfig) -> DatagenConfig:
    """Check value types and ranges, raising a one-line ConfigError naming the bad setting; returns ``cfg`` (its
    object set's folder made absolute and checked: ``sim.config.with_objects``)."""
    cfg = dataclasses.replace(cfg, workcell=with_objects(cfg.workcell))
    _check_range("blocks", cfg.blocks, 1)
    check_block_types(cfg.block_types, cfg.workcell.objects)
    if not 0.01 <= cfg.min_spacing <= 0.2:
        raise ConfigError(f"min_spacing {cfg.min_spacing} m is out of range: use 0.01-0.2")
    if cfg.scene not in SCENES:
        raise ConfigError(f"scene (--scene) {cfg.scene!r} must be one of {', '.join(SCENES)}")
    _check_range("clutter.parts", cfg.clutter.parts, 1)
    if min(cfg.clutter.tote.inner_size) <= 0.0:
        raise ConfigError(f"clutter.tote.inner_size must be positive, got {list(cfg.clutter.tote.inner_size)}")
    for name, v in (("views", cfg.views), ("clutter_views", cfg.clutter_views)):
        _check_range(f"{name}.distance", v.distance, 0.05)
        _check_range(f"{name}.elevation_deg", v.elevation_deg, 0.0)
        _check_range(f"{name}.azimuth_deg", v.azimuth_deg)
        if v.elevation_deg[1] > 89.5:
            raise ConfigError(f"{name}.elevation_deg must stay below 89.5 degrees, got {list(v.elevation_deg)}")
        if v.ik_iters < 1 or v.attempts_per_view < 1:
            raise ConfigError(f"{name}.ik_iters and {name}.attempts_per_view must be >= 1")
    _check_range("lights.extra", cfg.lights.extra, 0)
    if cfg.lights.extra[1] > 6:
        raise ConfigError(f"lights.extra allows at most 6 extra lights (OpenGL renders 8), got {cfg.lights.extra[1]}")
    _check_range("distractors.count", cfg.distractors.count, 0)
    _check_range("distractors.size", cfg.distractors.size, 0.002)
    _check_range("distractors.band", cfg.distractors.band, 0.0)
    bad = sorted(set(cfg.textures.kinds) - set(TEXTURE_KINDS))
    if bad or not cfg.textures.kinds:
        raise ConfigError(f"textures.kinds {list(cfg.textures.kinds)} must be a non-empty subset of "
                          f"{list(TEXTURE_KINDS)}")
    if not cfg.colours.palette:
        raise ConfigError("colours.palette must hold at least one RGB colour")
    if cfg.rgb_format not in RGB_FORMATS:
        raise ConfigError(f"rgb_format {cfg.rgb_format!r} must be one of {', '.join(RGB_FORMATS)}")
    if not 0.01 <= cfg.depth_scale <= 10.0:
        raise ConfigError(f"depth_scale {cfg.depth_scale} is out of range: use 0.01-10 (png value x depth_scale = mm)")
    if cfg.msaa not in (0, 2, 4, 8):
        raise ConfigError(f"msaa must be 0, 2, 4 or 8 samples per pixel, got {cfg.msaa}")
    if not 1 <= cfg.jpg_quality <= 100:
        raise ConfigError(f"jpg_quality must be 1-100, got {cfg.jpg_quality}")
    return cfg


def load_datagen_config(path: str | Path | None = None) -> DatagenConfig:
    """Generation settings from a TOML file (defaults for anything it leaves out), validated."""
    return validate(load_toml(DatagenConfig, path))
