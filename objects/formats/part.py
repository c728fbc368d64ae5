"""A part as its file gives it, and the file types read (``objects.formats.read_part`` reads them)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import trimesh

from posegrasp import inputs
from posegrasp.errors import UserError
from posegrasp.surface import TexturedSurface

#: File types ``read_part`` reads (a BOP models folder is read by the importer).
FORMATS = (".stl", ".obj", ".ply", ".glb", ".gltf", ".step", ".stp", ".urdf")


@dataclass(frozen=True)
class Part:
    """A part as its file gives it: ``mesh`` (m, unprocessed), and its look: ``rgba`` when one colour says it,
    ``surface`` (m, the mesh's frame) when it has a texture or several colours, neither when the file says none;
    ``notes``: what of the file could not be used, in words (a material library it names but lacks)."""

    mesh: trimesh.Trimesh
    rgba: tuple[float, float, float, float] | None = None
    surface: TexturedSurface | None = None
    notes: tuple[str, ...] = ()


def check_file(path: Path) -> None:
    """Refuse a missing file or one of a type ``read_part`` does not read."""
    if not os.path.lexists(path):
        raise UserError(f"{path}: no such file")
    inputs.check_file(path, "mesh")  # a regular file, not too large
    if path.suffix.lower() not in FORMATS:
        raise UserError(f"{path}: unknown mesh format {path.suffix or '(no suffix)'!r}; use STL, OBJ, PLY, GLB, "
                        "GLTF, STEP or URDF (or a BOP models/ folder)")
