"""Mass properties and size of a solid mesh (SI units, in the mesh's frame)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial.distance import pdist


@dataclass(frozen=True)
class MassProperties:
    """A uniform solid: volume (m^3), mass (kg), centre of mass (3,) m, inertia (3, 3) about it (kg m^2),
    diameter (m, largest distance between two surface points, BOP's), bounding box min (3,) and size (3,) (m)."""

    volume: float
    mass: float
    center_of_mass: np.ndarray
    inertia: np.ndarray
    diameter: float
    min_xyz: np.ndarray
    extents: np.ndarray


def diameter(points: np.ndarray) -> float:
    """Largest distance (same unit) between two of ``points``: attained at convex-hull vertices."""
    hull = trimesh.convex.convex_hull(points)
    return float(pdist(np.asarray(hull.vertices)).max())


def mass_properties(mesh: trimesh.Trimesh, density: float) -> MassProperties:
    """``mesh`` (closed, outward, m) filled with ``density`` (kg/m^3): the divergence-theorem integrals."""
    return MassProperties(
        volume=float(mesh.volume), mass=float(mesh.volume * density),
        center_of_mass=np.asarray(mesh.center_mass, np.float64),
        inertia=np.asarray(mesh.moment_inertia, np.float64) * density,  # trimesh integrates at density 1
        diameter=diameter(np.asarray(mesh.vertices)),
        min_xyz=np.asarray(mesh.bounds[0], np.float64), extents=np.asarray(mesh.extents, np.float64))
