"""Reading a part's file: its triangles in metres and how it looks, one reader per format, chosen by suffix.

    .stl .ply .obj .glb .gltf   ``meshfile``: trimesh's readers; OBJ materials (MTL) and glTF textures kept
    .step .stp                  ``step``: tessellated by OpenCASCADE (cascadio), in the file's own unit
    .urdf                       ``urdf``: every link's visual meshes, placed, scaled and coloured

``read_part`` returns the triangles unprocessed (the repair comes after) and, where the file says how the part
looks, one colour or a textured surface (``posegrasp.surface``) in the same frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from posegrasp.errors import UserError
from posegrasp.objects.formats import meshfile, step, urdf
from posegrasp.objects.formats.part import FORMATS, Part, check_file

__all__ = ["FORMATS", "Part", "check_file", "read_part"]


def read_part(path: Path, metres_per_unit: float, step_tolerance: tuple[float, float] = (1e-4, 0.5),
              mesh_root: Path | None = None) -> Part:
    """The part in ``path``, scaled to metres by ``metres_per_unit`` (``--unit`` times ``--scale``; a STEP file
    is in its own declared unit first). ``step_tolerance``: tessellation's (linear m, angular rad) deflection;
    ``mesh_root``: the folder a URDF's meshes are found under (None: its package)."""
    check_file(path)
    suffix = path.suffix.lower()
    if suffix in (".step", ".stp"):
        part = step.read(path, *step_tolerance)
    elif suffix == ".urdf":
        part = urdf.read(path, mesh_root)
    else:
        part = meshfile.read(path)
    if len(part.mesh.faces) == 0:
        raise UserError(f"{path}: the file holds no triangles (empty mesh or a point cloud)")
    v = np.asarray(part.mesh.vertices, np.float64)  # NaN vertices are the repair's to drop (``objects.repair``)
    surface = None if part.surface is None else part.surface.moved(metres_per_unit)
    return Part(trimesh.Trimesh(v * metres_per_unit, np.asarray(part.mesh.faces, np.int64), process=False),
                part.rgba, surface, part.notes)
