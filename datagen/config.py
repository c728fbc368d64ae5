"""Settings of synthetic dataset generation: scene contents, viewpoints, domain randomisation, sensor noise.

Lengths in metres, angles in degrees where the name says ``_deg``, colours RGB in [0, 1]. Every field has a
default; a TOML file of the same layout (tables ``[views]``, ``[colours]``, ``[textures]``, ``[lights]``,
``[distractors]``, ``[depth_noise]``, ``[rgb_noise]``, ``[workcell]``) overrides any of them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import field
from pathlib import Path

from posegrasp.config import load_toml, settings, within
from posegrasp.errors import ConfigError
from posegrasp.sim.clutter import CLUTTER_KINDS, ClutterConfig
from posegrasp.sim.config import WorkcellConfig, check_pairs, with_objects
from posegrasp.sim.scene import PALETTE, check_block_types


SCENES = ("table", *CLUTTER_KINDS)  #: ``DatagenConfig.scene``'s kinds (``--scene``)
TEXTURE_KINDS = ("checker", "gradient", "flat", "noise")
RGB_FORMATS = ("auto", "jpg", "png")
MSAA = (0, 2, 4, 8)  #: multisamples per colour pixel ``DatagenConfig.msaa`` may take


@settings
class ViewConfig:
    """Hand-camera viewpoints on a spherical cap over the clutter, reached by the arm.

    The camera looks at a point among the blocks with image-up toward world-up, then rolls about its axis.
    """

    #: Range of the camera's distance (m) from the look-at point.
    distance: tuple[float, float] = field(default=(0.25, 0.75), metadata=within(0.05, 5.0))
    #: Range of the camera's elevation (deg) above the table plane.
    elevation_deg: tuple[float, float] = field(default=(30.0, 88.0), metadata=within(0.0, 89.5))
    #: Range of the azimuth (deg) about the vertical through the look-at point; 0: the arm base's side.
    azimuth_deg: tuple[float, float] = (-180.0, 180.0)
    #: Largest roll (deg) of the camera about its optical axis.
    roll_deg: float = 60.0
    #: Random offset (m) of the look-at point.
    target_jitter: float = 0.02
    #: A view whose IK position residual (m) exceeds this is unreachable.
    max_pos_residual: float = 0.005
    #: A view whose IK rotation residual (deg) exceeds this is unreachable.
    max_rot_residual_deg: float = 1.0
    #: Camera positions farther (m) from the shoulder joint are rejected without IK.
    max_reach: float = 0.66
    #: IK iterations per attempt.
    ik_iters: int = field(default=60, metadata=within(1, 10_000))
    #: IK attempts (random starts) per view.
    attempts_per_view: int = field(default=4, metadata=within(1, 1000))

    def __post_init__(self) -> None:
        check_pairs(self, "distance", "elevation_deg", "azimuth_deg")


@settings
class ColourConfig:
    """Block colours: a palette entry with hue, saturation and value jitter, and material ranges."""

    #: Base colours, RGB in [0, 1]: saturated toy colours and dull greys and browns.
    palette: tuple[tuple[float, float, float], ...] = PALETTE
    #: Hue jitter, a fraction of a full turn.
    hue_jitter: float = 0.03
    #: Saturation jitter.
    saturation_jitter: float = 0.15
    #: Value (brightness) jitter.
    value_jitter: float = 0.2
    #: Range of the material's specular reflectance.
    specular: tuple[float, float] = (0.05, 0.6)
    #: Range of the material's shininess.
    shininess: tuple[float, float] = (0.05, 0.7)

    def __post_init__(self) -> None:
        if not self.palette:
            raise ConfigError("ColourConfig.palette = [] must hold at least one RGB colour")


@settings
class TextureConfig:
    """Procedural table and floor textures in random colours."""

    #: Texture kinds drawn from: MuJoCo's `checker`, `gradient`, `flat`, or a generated `noise` image.
    kinds: tuple[str, ...] = TEXTURE_KINDS
    #: Range of the fraction of texels given random marks.
    speckle: tuple[float, float] = (0.0, 0.05)
    #: Range of the texture repeats per metre.
    repeat_per_m: tuple[float, float] = (1.0, 12.0)
    #: Side (px) of a generated texture.
    size_px: int = 64

    def __post_init__(self) -> None:
        if not self.kinds or not set(self.kinds) <= set(TEXTURE_KINDS):
            raise ConfigError(f"TextureConfig.kinds = {list(self.kinds)} must be a non-empty subset of "
                              f"{list(TEXTURE_KINDS)}")


@settings
class LightConfig:
    """Lights added to the workcell's two, then all placed, aimed and dimmed at random."""

    #: Range of the number of lights added (at most 6).
    extra: tuple[int, int] = field(default=(0, 3), metadata=within(0, 6))
    #: Range of each light's diffuse intensity.
    intensity: tuple[float, float] = (0.3, 0.8)
    #: Largest per-channel colour tint of a light.
    tint: float = 0.15

    def __post_init__(self) -> None:
        check_pairs(self, "extra")


@settings
class DistractorConfig:
    """Unlabelled primitives (box, cylinder, sphere, capsule) on the table around the pick area."""

    #: Range of the number of distractors per scene.
    count: tuple[int, int] = field(default=(0, 4), metadata=within(0, 100))
    #: Range of a distractor's half-extent (m).
    size: tuple[float, float] = field(default=(0.01, 0.045), metadata=within(0.002, 0.5))
    #: Range of the distance (m) from the pick area's edge.
    band: tuple[float, float] = field(default=(0.05, 0.15), metadata=within(0.0, 1.0))

    def __post_init__(self) -> None:
        check_pairs(self, "count", "size", "band")


@settings
class DepthNoiseConfig:
    """Structured-light depth sensor model.

    Projector shadows and dropout at depth edges, lateral jitter, axial noise
    ``sigma = sigma_base + sigma_quad (z - z_ref)^2 + sigma_angle / sqrt(z) theta^2 / (pi/2 - theta)^2``
    (z depth, theta the incidence angle), disparity quantisation and random dropout.
    """

    #: Apply the depth noise model.
    enabled: bool = True
    #: Axial noise std (m) at `z_ref`.
    sigma_base: float = 0.0008
    #: Growth (m per m^2) of the axial noise std with (z - z_ref)^2.
    sigma_quad: float = 0.0019
    #: Depth (m) of the least axial noise.
    z_ref: float = 0.4
    #: Weight (m) of the incidence-angle term of the axial noise.
    sigma_angle: float = 0.0001
    #: Std (px) of the lateral jitter.
    pixel_shift: float = 0.25
    #: Projector-camera baseline (m), for shadows and disparity.
    baseline: float = 0.05
    #: Disparity quantisation step (px).
    disparity_step: float = 0.125
    #: Depth jump (m) that makes a pixel a depth edge.
    edge_threshold: float = 0.01
    #: Probability that an edge pixel reads no depth.
    edge_dropout: float = 0.5
    #: Probability that any pixel reads no depth.
    random_dropout: float = 0.002
    #: Also write the noiseless depth to `depth_clean/`.
    keep_clean: bool = False


@settings
class RgbNoiseConfig:
    """Camera effects on the colour image: exposure, gamma, blur and sensor noise."""

    #: Apply the colour image effects.
    enabled: bool = True
    #: Range of the exposure gain.
    gain: tuple[float, float] = (0.75, 1.25)
    #: Range of the gamma.
    gamma: tuple[float, float] = (0.85, 1.15)
    #: Probability of a Gaussian blur.
    blur_prob: float = 0.3
    #: Range of the blur's sigma (px).
    blur_sigma: tuple[float, float] = (0.3, 1.2)
    #: Range of the Gaussian sensor noise std (grey levels).
    noise_std: tuple[float, float] = (0.0, 4.0)


@settings
class DatagenConfig:
    """Everything that decides the content of a generated dataset (besides seed, scene and view counts)."""

    #: Range of the number of blocks per scene, drawn uniformly.
    blocks: tuple[int, int] = field(default=(3, 8), metadata=within(1, 10_000))
    #: Object types (names in the object set) drawn from; empty: all.
    block_types: tuple[str, ...] = ()
    #: Least distance (m) between drop points in the plane; smaller gives piles and more occlusion.
    min_spacing: float = field(default=0.03, metadata=within(0.01, 0.2))
    #: Blocks must rest within this distance (m) of the pick area, else they are dropped again.
    area_margin: float = 0.04
    #: Depth PNG unit (mm): value x depth_scale = mm, as in BOP.
    depth_scale: float = field(default=0.1, metadata=within(0.01, 10.0))
    #: Colour image format: `jpg`, `png`, or `auto` (jpg for `train_pbr`, png otherwise).
    rgb_format: str = "auto"
    #: JPEG quality, 1-100.
    jpg_quality: int = field(default=95, metadata=within(1, 100))
    #: Multisamples per colour pixel (0, 2, 4 or 8; 0 is faster, with jagged edges).
    msaa: int = 4
    #: Viewpoints of the hand camera.
    views: ViewConfig = field(default_factory=ViewConfig)
    #: Block colours.
    colours: ColourConfig = field(default_factory=ColourConfig)
    #: Table and floor textures.
    textures: TextureConfig = field(default_factory=TextureConfig)
    #: Lights.
    lights: LightConfig = field(default_factory=LightConfig)
    #: Unlabelled clutter.
    distractors: DistractorConfig = field(default_factory=DistractorConfig)
    #: The depth sensor model.
    depth_noise: DepthNoiseConfig = field(default_factory=DepthNoiseConfig)
    #: The colour camera model.
    rgb_noise: RgbNoiseConfig = field(default_factory=RgbNoiseConfig)
    #: The workcell (`--objects` sets its `objects`).
    workcell: WorkcellConfig = field(default_factory=WorkcellConfig)
    #: Scene kind (``--scene``): ``table`` (blocks apart on the pick area), ``pile`` (a heap) or ``bin`` (a heap in a
    #: tote).
    scene: str = "table"
    #: Pile and bin scenes: parts per scene (``--blocks``; ``blocks`` is the table's), tote, drop and settling.
    clutter: ClutterConfig = field(default_factory=ClutterConfig)
    #: Viewpoints of pile and bin scenes: closer and steeper than the table's, to look into the tote.
    clutter_views: ViewConfig = field(default_factory=lambda: ViewConfig(distance=(0.3, 0.6),
                                                                          elevation_deg=(45.0, 88.0)))

    def __post_init__(self) -> None:
        check_pairs(self, "blocks")
        for key, allowed in (("scene", SCENES), ("rgb_format", RGB_FORMATS), ("msaa", MSAA)):
            if getattr(self, key) not in allowed:
                raise ConfigError(f"DatagenConfig.{key} = {getattr(self, key)!r} must be one of "
                                  f"{', '.join(map(str, allowed))}")


def validate(cfg: DatagenConfig) -> DatagenConfig:
    """``cfg`` with its object set's folder made absolute and checked (``sim.config.with_objects``) and its
    ``block_types`` found in that set, else a one-line ConfigError; the settings check their own values when built."""
    cfg = dataclasses.replace(cfg, workcell=with_objects(cfg.workcell))
    check_block_types(cfg.block_types, cfg.workcell.objects)
    return cfg


def load_datagen_config(path: str | Path | None = None) -> DatagenConfig:
    """Generation settings from a TOML file (defaults for anything it leaves out), validated."""
    return validate(load_toml(DatagenConfig, path))
