"""The tray: a flat plate on the place area with one slot per part, each slot a pose (position and turn about the
vertical, tray frame) and the part type it takes, as a kitting tray or a machine's fixture plate holds them.

Composed as its own ``dm_control.mjcf`` model and attached to the workcell at the tray's centre, so its geoms are
named ``tray/plate`` and ``tray/slot_0`` ... (flat, drawn marks on the plate, which nothing collides with). The tray
frame is the world frame moved to the plate's centre on the table: slot ``(x, y)`` in metres, ``yaw_deg`` about +z.
With ``second_look`` the model also holds ``tray/part_camera``: an RGB-D camera on the table beside the plate looking
straight up (its OpenCV frame is the tray frame moved to ``look_camera_xy``: x along world x, z up), with a light
beside it, that sees a held part from below before it is set down (real cells do this).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from dm_control import mjcf

from posegrasp.config import settings, within
from posegrasp.errors import ConfigError

TRAY = "tray"  #: model name of the tray: the prefix of its geoms' names in a workcell
PART_CAMERA = "part_camera"  #: the upward camera of the second look (``tray/part_camera`` in a workcell)


@settings
class Slot:
    """One slot of the tray: the part type it takes and the pose (tray frame) its part is set down at."""

    #: The part type's name in the object set.
    type: str = "cube"
    #: Position (m) of the part's model frame origin over the plate, tray frame.
    xy: tuple[float, float] = field(default=(0.0, 0.0), metadata=within(-1.0, 1.0))
    #: Turn (deg) of the part's model frame about the vertical.
    yaw_deg: float = field(default=0.0, metadata=within(-360.0, 360.0))


def _grid(types: tuple[str, ...], columns: int, pitch: tuple[float, float]) -> tuple[Slot, ...]:
    """Slots of ``types`` row by row on a grid of ``columns`` columns, ``pitch`` (m) apart, centred on the tray."""
    rows = -(-len(types) // columns)
    return tuple(Slot(t, ((i % columns - 0.5 * (columns - 1)) * pitch[0], (i // columns - 0.5 * (rows - 1)) *
                                pitch[1])) for i, t in enumerate(types))


#: The default kit: twelve parts of the shipped blocks, every type at least once.
DEFAULT_KIT = ("cube", "long_cuboid", "brick_2x4", "brick_2x2", "cylinder", "triangular_prism", "arch", "l_block",
               "cube", "brick_2x2", "cylinder", "brick_2x4")


@settings
class TrayConfig:
    """The tray's plate and its slots; a part goes into a free slot of its type."""

    #: Plate size (m) along world x and y.
    size: tuple[float, float] = field(default=(0.36, 0.26), metadata=within(0.02, 2.0))
    #: Plate thickness (m): its top is this high above the table.
    thickness: float = field(default=0.006, metadata=within(0.001, 0.1))
    #: Offset (m) of the plate's centre from the place area's centre (world x, y).
    offset: tuple[float, float] = field(default=(0.0, 0.0), metadata=within(-2.0, 2.0))
    #: Colour (RGBA in [0, 1]) of the plate.
    rgba: tuple[float, float, float, float] = (0.75, 0.72, 0.62, 1.0)
    #: The slots (``[[bin_pick.tray.slots]]`` tables): ``type`` (a part type's name), ``xy`` (m, the part's model
    #: origin over the plate, tray frame), ``yaw_deg`` (its model frame's turn about the vertical).
    slots: tuple[Slot, ...] = _grid(DEFAULT_KIT, 4, (0.085, 0.085))
    #: A second look at each held part, from below, before it is set down: the part is set down as that look sees
    #: it held (``grasping.tasks.bin_pick.tray``), not as the look into the tote saw it at the pick.
    second_look: bool = False
    #: The provider's estimates at the second look give the held pose: the one nearest where the pick put the part.
    look_provider: bool = True
    #: Where they hold none near (or ``look_provider`` is false), the part's pose in the hand is shifted onto the
    #: look's depth image from there (``perception.held``: ICP against its model).
    look_fit: bool = True
    #: Position (m, tray frame) on the table of the second look's upward camera (off the plate).
    look_camera_xy: tuple[float, float] = field(default=(0.23, -0.16), metadata=within(-2.0, 2.0))
    #: The held part's estimated centre this far (m) above the upward camera at the second look.
    look_height: float = field(default=0.2, metadata=within(0.08, 1.0))

    def __post_init__(self) -> None:
        if not self.slots:
            raise ConfigError("bin_pick.tray.slots is empty: give the tray one slot per part ([[bin_pick.tray.slots]])")
        if not (self.look_provider or self.look_fit):
            raise ConfigError("bin_pick.tray: look_provider and look_fit are both false, so the second look sees "
                              "nothing: set one true")
        half = 0.5 * np.asarray(self.size)
        if self.second_look and np.all(np.abs(self.look_camera_xy) < half):
            raise ConfigError(f"bin_pick.tray.look_camera_xy {list(self.look_camera_xy)} lies on the plate: move the "
                              "camera off it (tray frame, m)")
        for i, s in enumerate(self.slots):
            if np.any(np.abs(s.xy) > half):
                raise ConfigError(f"bin_pick.tray.slots[{i}] at {list(s.xy)} lies off the {self.size[0]:g} x "
                                  f"{self.size[1]:g} m plate: move it inside or make bin_pick.tray.size larger")


@dataclass(frozen=True)
class Tray:
    """The tray on the table: ``center`` (x, y, m, world) of its plate, and its settings."""

    cfg: TrayConfig
    center: tuple[float, float]

    @property
    def top_z(self) -> float:
        """Height (m) of the plate's top above the table."""
        return self.cfg.thickness

    def slot_pose(self, i: int) -> tuple[np.ndarray, float]:
        """Slot ``i``'s position (x, y, m, world) and turn (rad) about the vertical."""
        s = self.cfg.slots[i]
        return np.asarray(self.center) + np.asarray(s.xy), float(np.radians(s.yaw_deg))

    def holds(self, points: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """Per world point (N, 3): does it lie over the plate (within ``tol``, m) and above its top less ``tol``?"""
        p = np.asarray(points, float).reshape(-1, 3)
        half = 0.5 * np.asarray(self.cfg.size) + tol
        return np.all(np.abs(p[:, :2] - self.center) <= half, axis=1) & (p[:, 2] >= self.top_z - tol)

    def check_layout(self, radii: dict[str, float]) -> None:
        """ConfigError unless every slot's type has a radius (``radii``: the object set's part types, m, the
        largest distance from the model origin to a vertex) and no two slots' parts can overlap."""
        for i, s in enumerate(self.cfg.slots):
            if s.type not in radii:
                raise ConfigError(f"bin_pick.tray.slots[{i}].type {s.type!r} is not a part type of the object set; "
                                  f"choose one of: {', '.join(sorted(radii))}")
        for (i, a), (j, b) in itertools.combinations(enumerate(self.cfg.slots), 2):
            gap = float(np.hypot(*np.subtract(a.xy, b.xy))) - radii[a.type] - radii[b.type]
            if gap < 0.0:
                raise ConfigError(f"bin_pick.tray.slots[{i}] ({a.type}) and [{j}] ({b.type}) overlap by "
                                  f"{-1000 * gap:.0f} mm: move them apart")

    def mjcf_model(self) -> mjcf.RootElement:
        """The tray as its own MJCF model, in a frame at the plate's centre on the table: the plate and a flat mark
        (drawn only) at each slot, its longer side along the slot's yaw."""
        c = self.cfg
        root = mjcf.RootElement(model=TRAY)
        root.worldbody.add("geom", name="plate", type="box", size=(0.5 * c.size[0], 0.5 * c.size[1], 0.5 * c.thickness),
                           pos=(0, 0, 0.5 * c.thickness), rgba=c.rgba, contype=1, conaffinity=1, group=1,
                           friction=(0.9, 0.01, 0.001))
        for i, s in enumerate(c.slots):
            root.worldbody.add("geom", name=f"slot_{i}", type="box", size=(0.012, 0.003, 0.0002),
                               pos=(*s.xy, c.thickness + 0.0002), rgba=(0.3, 0.3, 0.3, 1),
                               quat=(np.cos(np.radians(0.5 * s.yaw_deg)), 0, 0, np.sin(np.radians(0.5 * s.yaw_deg))),
                               contype=0, conaffinity=0, group=1)
        if c.second_look:  # OpenCV frame = tray frame at the camera (z up); MuJoCo's camera looks along its -z
            x, y = c.look_camera_xy
            root.worldbody.add("camera", name=PART_CAMERA, pos=(x, y, 0.02), quat=(0.0, 1.0, 0.0, 0.0))
            root.worldbody.add("geom", name="part_camera_housing", type="box", size=(0.03, 0.02, 0.01),
                               pos=(x, y, 0.01), rgba=(0.12, 0.12, 0.14, 1), contype=0, conaffinity=0, group=1)
            root.worldbody.add("light", name="part_light", pos=(x + 0.05, y, 0.03), dir=(0.0, 0.0, 1.0),
                               diffuse=(0.6, 0.6, 0.6), castshadow=False, cutoff=50)
        return root

    def add_to(self, root: mjcf.RootElement) -> None:
        """Attach the tray to a workcell's MJCF ``root`` (static), its plate's centre at ``center`` on the table."""
        root.attach(self.mjcf_model()).pos = (*self.center, 0.0)
