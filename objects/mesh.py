"""Reading a mesh file and making it a closed, outward-oriented solid in metres (``objects.repair``), centred on its
bounding box. A mesh with no volume or of the wrong size is refused with one line naming the file and the defect
(``UserError``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from posegrasp.errors import UserError
from posegrasp.objects.repair import repair

#: Metres per unit of ``--unit``.
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}


@dataclass(frozen=True)
class SolidMesh:
    """A repaired mesh (m) centred on its bounding box: ``vertices_obj = vertices_file * scale + offset``."""

    mesh: trimesh.Trimesh
    scale: float  # metres per file unit
    offset: np.ndarray  # (3,) translation applied after scaling (m)
    repairs: tuple[str, ...]  # what was repaired, in words
    volume_change: float = 0.0  # the solid's volume over the input surface's, minus 1
    surface: trimesh.Trimesh | None = None  # the input surface (m, same frame) to draw a remeshed solid with


def check_size(mesh: trimesh.Trimesh, name: str, unit: str, lo: float, hi: float) -> None:
    """Refuse a mesh whose bounding-box diagonal (m) lies outside [lo, hi]: its declared unit is likely wrong."""
    v = np.asarray(mesh.vertices)[np.unique(np.asarray(mesh.faces))]
    v = v[np.isfinite(v).all(axis=1)]
    if len(v) == 0:
        raise UserError(f"{name}: every vertex coordinate is NaN or infinite; nothing to import")
    diag = float(np.linalg.norm(np.ptp(v, axis=0)))
    if lo <= diag <= hi:
        return
    sizes = {u: diag / UNITS[unit] * s for u, s in UNITS.items()}
    fits = sorted((u for u, d in sizes.items() if lo <= d <= hi), key=lambda u: abs(np.log(sizes[u] / 0.1)))
    hint = f"; is it in {fits[0]}? pass --unit {fits[0]}" if fits else ""
    raise UserError(f"{name}: {diag:.4g} m across with --unit {unit}, outside the {lo:g}-{hi:g} m a tabletop part "
                    f"spans{hint}")


def centred(raw: trimesh.Trimesh, scale: float, label: str, unit: str, max_hole_fraction: float,
            size_range: tuple[float, float], remesh_cells: int = 64) -> SolidMesh:
    """Size-check and repair ``raw`` (m), then move its bounding-box centre to the origin (``label`` names the mesh
    in error messages)."""
    check_size(raw, label, unit, *size_range)
    fixed = repair(raw, label, max_hole_fraction, remesh_cells)
    mesh, repairs = fixed.mesh, fixed.repairs
    offset = -mesh.bounds.mean(axis=0)
    mesh.apply_translation(offset)
    surface = None if fixed.surface is None else fixed.surface.copy().apply_translation(offset)
    return SolidMesh(mesh=mesh, scale=scale, offset=offset, repairs=repairs, volume_change=fixed.volume_change,
                     surface=surface)
