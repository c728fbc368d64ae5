"""Typed settings of the mesh import (``posegrasp objects import --config FILE``, any field from TOML).

Lengths are relative where the name says ``_rel`` (a fraction of the object's diameter), else in metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from posegrasp.config import within


@dataclass(frozen=True)
class ImportConfig:
    """How meshes become objects: physical defaults, repair limits, symmetry search and decomposition."""

    #: Density (kg/m^3) of every object; the default is ABS plastic (`--density`).
    density: float = field(default=1050.0, metadata=within(1.0, 25000.0))
    #: MuJoCo friction: sliding, torsional, rolling.
    friction: tuple[float, float, float] = (0.5, 0.005, 0.0001)
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
