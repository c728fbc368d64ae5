"""Typed settings of the mesh import (``posegrasp objects import --config FILE``: an ``[import]`` table, any field
from TOML; ``[import.fit]`` the workcell the parts are checked against).

Lengths are relative where the name says ``_rel`` (a fraction of the object's diameter), else in metres.
"""

from __future__ import annotations

import sys
from dataclasses import field
from pathlib import Path

import numpy as np

from posegrasp.config import load_toml, read_toml, settings, within
from posegrasp.errors import ConfigError

#: The TOML table of the import settings.
TABLE = "import"


@settings
class FitCheckConfig:
    """The workcell each part is checked against (a warning per misfit): the shipped workcell's and grasp settings'
    values (``tests/test_objects.py`` holds them equal); change them for another hand or camera."""

    #: The fingers' smallest and largest span (m): the grasp settings' ``min_width`` and ``max_width``.
    hand_span: tuple[float, float] = field(default=(0.012, 0.085), metadata=within(0.0, 1.0))
    #: Half the pick area's size along x and y (m): the workcell's ``pick_area.half_size``.
    pick_area_half_size: tuple[float, float] = field(default=(0.12, 0.15), metadata=within(0.01, 2.0))
    #: Hand camera image height (px): the workcell's ``hand_camera.height``.
    camera_height: int = field(default=480, metadata=within(16, 4096))
    #: Hand camera vertical field of view (deg): the workcell's ``hand_camera.fovy_deg``.
    camera_fovy_deg: float = field(default=55.0, metadata=within(1.0, 170.0))
    #: Hand camera height above the pick area at the look pose (m): the workcell's ``look_height``.
    look_height: float = field(default=0.38, metadata=within(0.01, 5.0))

    def __post_init__(self) -> None:
        if self.hand_span[0] > self.hand_span[1]:
            raise ConfigError(f"FitCheckConfig.hand_span = {list(self.hand_span)}: give the smallest span first")

    @property
    def focal_px(self) -> float:
        """The hand camera's focal length (px)."""
        return float(self.camera_height / 2 / np.tan(np.deg2rad(self.camera_fovy_deg) / 2))


@settings
class ImportConfig:
    """How meshes become objects: physical defaults, repair limits, symmetry search and decomposition."""

    #: Density (kg/m^3) of every object; the default is ABS plastic (`--density`).
    density: float = field(default=1050.0, metadata=within(1.0, 25000.0))
    #: MuJoCo friction: sliding, torsional, rolling.
    friction: tuple[float, float, float] = (0.5, 0.005, 0.0001)
    #: The folder a URDF's meshes are found under, never outside it (``package://NAME/`` paths in it or in its folder
    #: ``NAME``); empty: the URDF's package, its folder and the one above (`--mesh-root`).
    mesh_root: str = ""
    #: STEP tessellation: largest distance (m) between a triangle and the true surface it stands for.
    step_linear_tolerance: float = field(default=1e-4, metadata=within(1e-6, 0.01))
    #: STEP tessellation: largest angle (rad) between the normals of neighbouring triangles on a curved face.
    step_angular_tolerance: float = field(default=0.5, metadata=within(0.01, 1.5))
    #: Largest hole patch closed, a fraction of the surface area; a larger opening is refused.
    max_hole_fraction: float = field(default=0.25, metadata=within(0.0, 1.0))
    #: Cells across the bounding-box diagonal of the watertight remesh of a mesh local repairs cannot close.
    remesh_cells: int = field(default=64, metadata=within(16, 256))
    #: Smallest bounding-box diagonal (m); smaller means the declared unit is wrong.
    min_size: float = 0.005
    #: Largest bounding-box diagonal (m); larger means the declared unit is wrong.
    max_size: float = 1.0
    #: A symmetry moves every checked surface point within this fraction of the diameter of the surface.
    sym_tol_rel: float = field(default=0.01, metadata=within(1e-5, 0.2))
    #: Surface samples checked per symmetry candidate.
    sym_points: int = field(default=1500, metadata=within(100, 100000))
    #: Highest n of an n-fold symmetry axis searched.
    max_fold: int = field(default=24, metadata=within(2, 360))
    #: Most collision pieces per object.
    max_pieces: int = field(default=32, metadata=within(1, 256))
    #: CoACD concavity threshold.
    coacd_threshold: float = field(default=0.05, metadata=within(0.01, 1.0))
    #: Most triangles of the solid handed to CoACD (decimated to this; its pieces need no finer surface).
    collision_faces: int = field(default=3000, metadata=within(200, 1_000_000))
    #: CoACD tree-search iterations per cut (its own default is 150: finer cuts, three times slower).
    coacd_iterations: int = field(default=50, metadata=within(10, 1000))
    #: Seed of CoACD and the surface samples: the same mesh gives the same pieces.
    seed: int = 0
    #: Trial tasks that hold the set's objects firmly, written into the set's manifest.
    firm_hold_tasks: tuple[str, ...] = ("pick-place", "kitting", "stack")
    #: Warn when the object spans fewer pixels (px) in the hand camera at the look pose.
    min_pixels: float = 16.0
    #: The workcell the parts are checked against.
    fit: FitCheckConfig = field(default_factory=FitCheckConfig)

    def __post_init__(self) -> None:
        if not self.min_size < self.max_size:
            raise ConfigError(f"ImportConfig.min_size = {self.min_size:g} m is not below max_size = "
                              f"{self.max_size:g} m")


def load_import_config(path: str | Path | None) -> ImportConfig:
    """The import settings of TOML file ``path`` (defaults for None): its ``[import]`` table, or, in a file without
    one, its top-level keys (with a one-line notice on stderr naming the table)."""
    if path is None:
        return ImportConfig()
    data = read_toml(path)
    if isinstance(data.get(TABLE), dict) or not data:
        return load_toml(ImportConfig, path, TABLE, (TABLE,))
    cfg = load_toml(ImportConfig, path)
    print(f"posegrasp: note: {path}: import settings at the top level are now an [{TABLE}] table", file=sys.stderr)
    return cfg
