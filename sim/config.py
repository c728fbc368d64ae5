"""Typed settings of the workcell: table, areas, hand camera, rendering, scene randomisation.

Lengths in metres, angles in degrees where the name says ``_deg``. ``assets/workcell.toml`` ships
these defaults; any field can be overridden from a TOML file of the same layout.
"""

from __future__ import annotations

import dataclasses
from dataclasses import field
from pathlib import Path

from posegrasp import ASSETS
from posegrasp.config import load_toml, settings, within
from posegrasp.errors import ConfigError


def check_pairs(cfg: object, *names: str) -> None:
    """Refuse, with a ConfigError naming the key and its value, a field of the settings ``cfg`` among ``names`` that
    is no [min, max] range with min <= max."""
    for name in names:
        r = getattr(cfg, name)
        if len(r) != 2 or r[0] > r[1]:
            raise ConfigError(f"{type(cfg).__name__}.{name} = {list(r)} must be a [min, max] pair with min <= max")


@settings
class CameraConfig:
    """A pinhole RGB-D camera. ``mount_*`` give ``T_gripper_cam`` (OpenCV camera frame in the gripper frame).

    The gripper frame is the hand's pinch site: z along the approach direction, x across the fingers.
    ``mount_rpy_deg`` are extrinsic x-y-z rotations. Depth outside [near, far] reads 0 (invalid).
    """

    #: Image width (px).
    width: int = field(default=640, metadata=within(16, 4096))
    #: Image height (px).
    height: int = field(default=480, metadata=within(16, 4096))
    #: Vertical field of view (deg).
    fovy_deg: float = field(default=55.0, metadata=within(1.0, 170.0))
    #: Nearest valid depth (m); closer reads 0.
    near: float = field(default=0.15, metadata=within(0.001, 10.0))
    #: Farthest valid depth (m); farther reads 0.
    far: float = field(default=2.0, metadata=within(0.01, 100.0))
    #: Camera position (m) in the gripper frame.
    mount_pos: tuple[float, float, float] = field(default=(0.0, 0.065, -0.11), metadata=within(-1.0, 1.0))
    #: Camera orientation in the gripper frame (deg), extrinsic x-y-z rotations.
    mount_rpy_deg: tuple[float, float, float] = field(default=(12.0, 0.0, 0.0), metadata=within(-360.0, 360.0))

    def __post_init__(self) -> None:
        if not self.near < self.far:
            raise ConfigError(f"CameraConfig.near = {self.near!r} m is not nearer than far = {self.far!r} m: every "
                              "depth would read 0; use near < far")


@settings
class RenderConfig:
    """Renderer settings; shadows and reflections cost ~6x frame rate on the CPU, so they are off."""

    #: Render shadows (about 6x slower on a CPU).
    shadows: bool = False
    #: Render reflections.
    reflections: bool = False


@settings
class AreaConfig:
    """An axis-aligned rectangle on the table top: centre (x, y) and half sizes (m), world frame."""

    #: Centre (x, y) (m), world frame.
    center: tuple[float, float] = field(default=(0.45, 0.0), metadata=within(-5.0, 5.0))
    #: Half sizes along x and y (m).
    half_size: tuple[float, float] = field(default=(0.12, 0.15), metadata=within(0.005, 2.0))


#: Ambient (atmospheric) pressure (kPa): no vacuum pulls harder than this below it.
AMBIENT_KPA = 101.325


@settings
class SuctionConfig:
    """The vacuum tool of ``hand = "suction"`` (``sim.suction``): a bellows cup on the gripper axis, its rim centre
    at the gripper frame's origin when the bellows is at rest. Industrial defaults: a 20 mm cup at 60 kPa."""

    #: Diameter (m) of the cup's rim.
    diameter: float = field(default=0.02, metadata=within(0.005, 0.08))
    #: How far (m) the bellows gives along the approach axis before it is fully compressed.
    stroke: float = field(default=0.01, metadata=within(0.001, 0.03))
    #: Vacuum (kPa below ambient) the pump holds in a sealed cup.
    vacuum_kpa: float = field(default=60.0, metadata=within(0.1, 100.0))
    #: The pump's suction flow (L/min): the sealed cup and its hose evacuate in ``sim.suction.seal_time``.
    flow_lpm: float = field(default=20.0, metadata=within(0.1, 1000.0))
    #: The rim seals where every rim point lies this close (m) to the part's surface along the approach axis.
    seal_tolerance: float = field(default=0.0015, metadata=within(0.0001, 0.01))
    #: Friction coefficient of the rim on a part (shear and torsion the sealed cup resists).
    friction: float = field(default=0.5, metadata=within(0.01, 2.0))
    #: The hold is lost when the load times this factor exceeds what the vacuum resists.
    safety: float = field(default=2.0, metadata=within(1.0, 10.0))

    def __post_init__(self) -> None:
        if self.seal_tolerance >= self.diameter / 2:
            raise ConfigError(f"SuctionConfig.seal_tolerance = {self.seal_tolerance!r} m is no seal on a "
                              f"{self.diameter!r} m cup: use less than its radius")


#: The hybrid hand's slide (``sim.hybrid``; m along the gripper z axis from the pinch point, negative toward the
#: palm): where the cup's rim retracts to, 1 mm inside a bore in the palm (whose face lies at -0.072); how far past the
#: pinch point the 2-finger hand's fingertips reach at their farthest (at any finger angle); the least lead of the
#: extended rim past that reach.
HYBRID_RETRACTED_Z, FINGERTIP_REACH, HYBRID_MIN_LEAD = -0.073, 0.0097, 0.002
#: The palm's bore (m deep from the retracted rim) that holds the retracted cup and the stem above it, the stem (m)
#: left in the bore with the cup out, and the widest cup (m) the fingers' knuckles round the bore clear.
HYBRID_BORE, HYBRID_STEM_OVERLAP, HYBRID_MAX_DIAMETER = 0.118, 0.003, 0.03


@settings
class HybridConfig:
    """The slide of ``hand = "hybrid"`` (``sim.hybrid``): the 2-finger hand with the suction tool's cup (``suction``)
    between its fingers on an actuated slide along the gripper axis, retracted into the palm for a pinch, extended
    past the fingertips for a suction pick."""

    #: The slide's stroke (m): extended, the cup's rim lies this far past its retracted place (73 mm above the pinch
    #: point), at least 2 mm past the fingertips' farthest reach (9.7 mm below the pinch point): 84.7 mm or more.
    extension: float = field(default=0.088, metadata=within(0.01, 0.115))
    #: Speed (m/s) of the slide, out and in.
    extension_speed: float = field(default=0.25, metadata=within(0.01, 2.0))
    #: In a suction pick the fingers close round the extended cup, in its shadow (open, they would reach the tote's
    #: walls), as far as keeps them this far (m) from the cup and its stem.
    cup_room: float = field(default=0.003, metadata=within(0.0005, 0.05))

    def __post_init__(self) -> None:
        least = FINGERTIP_REACH + HYBRID_MIN_LEAD - HYBRID_RETRACTED_Z
        if self.extension < least:
            short = (FINGERTIP_REACH - HYBRID_RETRACTED_Z - self.extension) * 1e3
            raise ConfigError(f"HybridConfig.extension = {self.extension!r} m does not clear the fingertips: the "
                              f"extended rim lies {short:.1f} mm above their reach; use at least {least:.4f} m")


@settings
class WorkcellConfig:
    """Everything that defines the workcell; the world frame is the arm base on the table top, z up.

    ``objects``: the object set its scenes draw from (a set folder, ``--objects``; ``""``: the shipped blocks,
    ``posegrasp.catalog``).
    """

    #: Table half sizes x, y, z (m).
    table_half_size: tuple[float, float, float] = field(default=(0.55, 0.75, 0.02), metadata=within(0.005, 5.0))
    #: Table centre (x, y) (m), world frame.
    table_center: tuple[float, float] = field(default=(0.3, 0.0), metadata=within(-5.0, 5.0))
    #: Where scenes drop the blocks.
    pick_area: AreaConfig = field(default_factory=AreaConfig)
    #: The place pad.
    place_area: AreaConfig = field(default_factory=lambda: AreaConfig(center=(0.1, 0.45), half_size=(0.07, 0.07)))
    #: The RGB-D camera on the hand.
    hand_camera: CameraConfig = field(default_factory=CameraConfig)
    #: The fixed camera of the overview pictures.
    overview_camera: CameraConfig = field(default_factory=lambda: CameraConfig(fovy_deg=45.0))
    #: Overview camera position (m), world frame.
    overview_pos: tuple[float, float, float] = field(default=(1.45, -0.7, 1.05), metadata=within(-20.0, 20.0))
    #: Point the overview camera looks at (m), world frame.
    overview_target: tuple[float, float, float] = field(default=(0.25, 0.1, 0.2), metadata=within(-20.0, 20.0))
    #: Renderer settings.
    render: RenderConfig = field(default_factory=RenderConfig)
    #: Height (m) of the hand camera above the pick area at the look pose.
    look_height: float = field(default=0.38, metadata=within(0.05, 3.0))
    #: Arm joint angles (rad) at the start of a scene.
    home_qpos: tuple[float, ...] = field(default=(-0.37, 3.34, 5.10, 2.65, 1.64, 2.28), metadata=within(-10.0, 10.0))
    #: Physics time step (s).
    timestep: float = field(default=0.002, metadata=within(0.0001, 0.01))
    #: Object set folder the scenes draw from (`--objects`); "" is the shipped blocks.
    objects: str = ""
    #: The Jaco2's hand (``--hand``): ``3-finger`` (KG-3: finger 1 facing fingers 2 and 3, 74 mm across the squeeze
    #: axis), ``2-finger`` (KG-2: two of the same fingers facing each other, 23 mm across; it reaches parts lying
    #: against a tote's wall), ``suction`` (a bellows vacuum cup instead of fingers, ``suction``) or ``hybrid`` (the
    #: 2-finger hand with the cup between its fingers on a slide, ``hybrid``).
    hand: str = "3-finger"
    #: The vacuum tool of ``hand = "suction"`` and the cup of ``hand = "hybrid"``.
    suction: SuctionConfig = field(default_factory=SuctionConfig)
    #: The cup's slide of ``hand = "hybrid"``.
    hybrid: HybridConfig = field(default_factory=HybridConfig)

    def __post_init__(self) -> None:
        narrow = 2.0 * min(self.pick_area.half_size)
        if self.suction.diameter >= narrow:
            raise ConfigError(f"WorkcellConfig.suction.diameter = {self.suction.diameter!r} m is no cup for a "
                              f"{narrow!r} m wide pick area: use a smaller cup")
        if self.hand == "hybrid":
            _check_hybrid(self)


def _check_hybrid(cfg: WorkcellConfig) -> None:
    """Refuse, in one line, a hybrid hand whose retracted cup (``suction``) and slide (``hybrid``) do not fit in the
    palm's bore or between the fingers' knuckles."""
    height, ext = 2.0 * cfg.suction.stroke, cfg.hybrid.extension  # the bellows at rest: twice its stroke
    room = HYBRID_BORE - HYBRID_STEM_OVERLAP - height
    if ext > room:
        raise ConfigError(f"WorkcellConfig.hybrid.extension = {ext!r} m is more than the slide allows: retracted, "
                          f"the {height * 1e3:.0f} mm cup and the stem above it fill the palm's "
                          f"{HYBRID_BORE * 1e3:.0f} mm bore; use at most {room:.4f} m or a shorter bellows stroke")
    if cfg.suction.diameter > HYBRID_MAX_DIAMETER:
        raise ConfigError(f"WorkcellConfig.suction.diameter = {cfg.suction.diameter!r} m is no cup between the "
                          f"hybrid hand's fingers: use at most {HYBRID_MAX_DIAMETER!r} m")


#: The hands ``WorkcellConfig.hand`` may name.
HANDS = ("3-finger", "2-finger", "suction", "hybrid")

DEFAULT_TOML = ASSETS / "workcell.toml"


def workcell_record(d: dict) -> dict:
    """A ``WorkcellConfig``'s ``dataclasses.asdict`` ``d`` as records keep it: the cup's settings only for the hands
    with one (``suction`` and ``hybrid``), the slide's only for ``hybrid`` (the records of the fingered hands stay
    those they were before the tools existed)."""
    keep = {"suction": ("suction",), "hybrid": ("suction", "hybrid")}.get(d.get("hand"), ())
    return {k: v for k, v in d.items() if k not in ("suction", "hybrid") or k in keep}


def load_workcell_config(path: str | Path | None = None) -> WorkcellConfig:
    """Workcell settings from ``path``, or the shipped ``assets/workcell.toml``."""
    return load_toml(WorkcellConfig, path if path is not None else DEFAULT_TOML)


def with_objects(cfg: WorkcellConfig, objects: str | Path | None = None) -> WorkcellConfig:
    """``cfg`` drawing from the object set ``objects`` (None: ``cfg.objects``, as a TOML file gave it), its folder
    made absolute (worker processes may run elsewhere) and checked: a one-line ``UserError`` for a missing
    folder, a missing or inconsistent file, or a BOP dataset given instead of a set."""
    from posegrasp.catalog import load_catalog

    name = cfg.objects if objects is None else str(objects)
    if not name:
        return dataclasses.replace(cfg, objects="")
    root = Path(name).expanduser().resolve()
    load_catalog(root)
    return dataclasses.replace(cfg, objects=str(root))
