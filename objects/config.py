"""Typed settings of the mesh import (``posegrasp objects import --config FILE``, any field from TOML).

Lengths are relative where the name says ``_rel`` (a fraction of the object's diameter), else in metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from posegrasp.config import within


@dataclass(frozen=True)
class ImportConfig:
    """How meshes become objects: physical defaults, repair limits, symmetry search and decomposition."""

    density: float = field(default=1050.0, metadata=within(1.0, 25000.0))  # kg/m^3 (ABS plastic)
    friction: tuple[float, float, float] = (0.5, 0.005, 0.0001)  # MuJoCo sliding, torsional, rolling
    max_hole_fraction: float = field(default=0.25, metadata=within(0.0, 1.0))  # close a hole only if its patch
    # area is at most this fraction of the surface area; a larger opening is refused
    min_size: float = 0.005  # a part's bounding-box diagonal must lie in [min_size, max_size] (m), else the
    max_size: float = 1.0  # declared unit is taken to be wrong
    sym_tol_rel: float = field(default=0.01, metadata=within(1e-5, 0.2))  # a symmetry moves every checked
    # surface point to within this fraction of the diameter of the surface
    sym_points: int = field(default=1500, metadata=within(100, 100000))  # surface samples checked per candidate
    max_fold: int = field(default=24, metadata=within(2, 360))  # highest n of an n-fold axis searched
    max_pieces: int = field(default=32, metadata=within(1, 256))  # cap on collision pieces per object
    coacd_threshold: float = field(default=0.05, metadata=within(0.01, 1.0))  # CoACD concavity threshold
    seed: int = 0  # CoACD's and the surface samples' seed: same mesh, same pieces
    # the trial tasks that hold the set's objects firmly (``TrialConfig.firm_hold_tasks``, written into the
    # set's manifest): all of them, since parts slip out of the plain pinch that the shipped blocks keep in
    # pick-and-place (seven imported parts, oracle pick-and-place: 186/200 firm, 163/200 plain; docs/objects.md)
    firm_hold_tasks: tuple[str, ...] = ("pick-place", "kitting", "stack")
    min_pixels: float = 16.0  # warn when the object spans fewer pixels in the hand camera at the look pose
