"""STL, PLY, OBJ (+MTL), GLB and glTF files through trimesh: the triangles, and the look the file gives them.

A texture (OBJ ``map_Kd``, glTF ``baseColorTexture``) becomes a textured surface; vertex or face colours, or several
material colours, are baked into one (``posegrasp.surface.baked``); one colour for the whole part is ``Part.rgba``. A
texture or glTF buffer the part names but that is missing is refused rather than silently dropped; an OBJ's missing
material library (MTL) only says how it looks (public assets ship OBJs naming an MTL they lack), so the part is read
without it and ``Part.notes`` says so.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import trimesh

from posegrasp.errors import UserError
from posegrasp.objects.formats.part import Part
from posegrasp.surface import TexturedSurface, baked, merged


def unread_materials(path: Path) -> tuple[str, ...]:
    """One sentence per material library (MTL) the OBJ ``path`` names that is not beside it (read without it)."""
    if path.suffix.lower() != ".obj":
        return ()
    return tuple(f"{path.name} names the material library {lib!r}, which is not in {path.parent}: read without its "
                 "materials" for lib in re.findall(r"^\s*mtllib\s+(.+?)\s*$", path.read_text(errors="replace"), re.M)
                 if not (path.parent / lib).is_file())


def _missing_files(path: Path) -> list[str]:
    """Texture files an OBJ's material libraries, or buffers and images a glTF, name that are not beside it."""
    names: list[str] = []
    suffix = path.suffix.lower()
    if suffix == ".obj":
        text = path.read_text(errors="replace")
        for lib in re.findall(r"^\s*mtllib\s+(.+?)\s*$", text, re.M):
            mtl = path.parent / lib
            if not mtl.is_file():
                continue
            names += [m for m in re.findall(r"^\s*map_Kd\s+(?:-\S+\s+\S+\s+)*(.+?)\s*$", mtl.read_text(errors="replace"),
                                            re.M) if not (mtl.parent / m).is_file()]
    elif suffix == ".gltf":
        try:
            doc = json.loads(path.read_text(errors="replace"))
        except json.JSONDecodeError:
            return []  # the reader says what is wrong
        for item in doc.get("buffers", []) + doc.get("images", []):
            uri = item.get("uri", "") if isinstance(item, dict) else ""
            if uri and not uri.startswith("data:") and not (path.parent / uri).is_file():
                names.append(uri)
    return names


def _image(material) -> np.ndarray | None:
    """The material's colour texture as (H, W, 3) uint8, or None."""
    img = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
    return None if img is None else np.asarray(img.convert("RGB"), np.uint8)


def _colour(material) -> np.ndarray:
    """The material's main colour, RGBA uint8."""
    return np.asarray(material.main_color, np.uint8)


def look(mesh: trimesh.Trimesh) -> TexturedSurface | np.ndarray | None:
    """How ``mesh`` looks: a textured surface, one RGBA uint8 colour, or None when its file gives no colour."""
    vis = mesh.visual
    faces = np.asarray(mesh.faces)
    if vis.kind == "texture":
        img = _image(vis.material)
        if img is not None and vis.uv is not None and len(vis.uv) == len(mesh.vertices):
            return TexturedSurface(np.asarray(mesh.vertices, np.float64), faces, np.asarray(vis.uv, np.float64), img)
        return _colour(vis.material)
    if vis.kind == "face":
        rgb = np.asarray(vis.face_colors, np.uint8)[:, :3]
    elif vis.kind == "vertex":
        rgb = np.asarray(vis.vertex_colors, np.float64)[faces][:, :, :3].mean(axis=1).round().astype(np.uint8)
    else:
        return None
    if (rgb == rgb[0]).all():
        return np.array([*rgb[0], 255], np.uint8)
    return baked(mesh.vertices, faces, rgb)


def combined(meshes: list[trimesh.Trimesh], looks: list[TexturedSurface | np.ndarray | None]) -> Part:
    """One part from several meshes (m, one frame) and their looks: one colour when they share one, else a textured
    surface (a mesh without a colour shown in ``default``'s grey)."""
    mesh = trimesh.util.concatenate([trimesh.Trimesh(m.vertices, m.faces, process=False) for m in meshes]) \
        if len(meshes) > 1 else trimesh.Trimesh(meshes[0].vertices, meshes[0].faces, process=False)
    if all(lk is None for lk in looks):
        return Part(mesh)
    colours = {tuple(lk.tolist()) for lk in looks if isinstance(lk, np.ndarray)}
    if len(colours) == 1 and all(isinstance(lk, np.ndarray) for lk in looks):
        return Part(mesh, rgba=tuple(float(c) / 255.0 for c in colours.pop()))
    grey = np.array([204, 204, 204, 255], np.uint8)
    parts = []
    for m, lk in zip(meshes, looks):
        if isinstance(lk, TexturedSurface):
            parts.append(lk)
        else:
            rgb = (grey if lk is None else lk)[:3]
            parts.append(baked(m.vertices, m.faces, np.tile(rgb, (len(m.faces), 1))))
    return Part(mesh, surface=merged(parts))


def read(path: Path) -> Part:
    """The part in an STL, PLY, OBJ, GLB or glTF file, in the file's units, its bodies in one mesh."""
    missing = _missing_files(path)
    if missing:
        raise UserError(f"{path}: names {missing[0]!r}, which is not in {path.parent}; copy it beside the file")
    try:
        loaded = trimesh.load(path, process=False)
        if isinstance(loaded, trimesh.Scene):
            meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
        else:
            meshes = [loaded] if isinstance(loaded, trimesh.Trimesh) and len(loaded.faces) else []
    except Exception as e:  # trimesh raises many types on corrupt files
        why = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise UserError(f"{path}: cannot read it as {path.suffix[1:].upper()}: {why}") from None
    if not meshes:
        raise UserError(f"{path}: the file holds no triangles (empty mesh or a point cloud)")
    for m in meshes:  # an index out of range (a negative one would wrap to a real vertex)
        f = np.asarray(m.faces)
        if f.min() < 0 or f.max() >= len(m.vertices):
            bad = int(f.min() if f.min() < 0 else f.max())
            raise UserError(f"{path}: a face names vertex {bad}, not one of its {len(m.vertices)} vertices")
    notes = unread_materials(path)
    if len(meshes) == 1 and meshes[0].visual.kind is None:
        return Part(trimesh.Trimesh(meshes[0].vertices, meshes[0].faces, process=False), notes=notes)
    return dataclasses.replace(combined(meshes, [look(m) for m in meshes]), notes=notes)
