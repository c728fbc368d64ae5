"""URDF parts: every link's visual geometry (meshes, boxes, cylinders, spheres), placed where the links stand with
all joints at zero, with its origin, scale and material colour. Collision geometry is ignored (the importer makes
its own from the visual), except in a URDF without any visual (pybullet_data's ``sphere_1cm.urdf``): then the
collision geometry is the part's shape, and the notes say so. Mesh paths (relative, ``package://PKG/rest``) resolve
under one root folder, never outside it (``_mesh_path``): the one the user names (``ImportConfig.mesh_root``,
``--mesh-root``), by default the URDF's package (its folder and the one above).
"""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import trimesh

from posegrasp.errors import UserError
import posegrasp.objects.formats.meshfile as meshfile
from posegrasp.objects.formats.part import Part, check_file


def _floats(text: str | None, n: int, default: float, where: str) -> np.ndarray:
    if text is None:
        return np.full(n, default)
    try:
        v = np.array([float(x) for x in text.split()])
    except ValueError:
        v = np.zeros(0)
    if v.size == 1 and n == 3:
        v = np.repeat(v, 3)
    if v.size != n or not np.isfinite(v).all():
        raise UserError(f"{where}: {text!r} is not {n} finite numbers")
    return v


def _origin(elem: ET.Element | None, where: str) -> np.ndarray:
    """4x4 of an ``<origin xyz rpy>`` (fixed-axis roll, pitch, yaw: R = Rz(yaw) Ry(pitch) Rx(roll))."""
    T = np.eye(4)
    if elem is None:
        return T
    r, p, y = _floats(elem.get("rpy"), 3, 0.0, where)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    T[:3, :3] = [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                 [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                 [-sp, cp * sr, cp * cr]]
    T[:3, 3] = _floats(elem.get("xyz"), 3, 0.0, where)
    return T


def _mesh_path(urdf: Path, name: str, where: str, root: Path | None = None) -> Path:
    """The file a mesh ``filename`` names, looked up beside the URDF and under ``root`` (default: the URDF's package,
    the folder above its own: ``meshes/x.obj`` or ``../meshes/x.obj`` of a ``urdf/`` folder; ``package://NAME/...``
    in ``root`` or in a folder ``NAME`` in it), never outside ``root`` (an absolute path or one climbing out of it is
    not found)."""
    folder = urdf.absolute().parent
    root = (folder.parent if root is None else Path(root)).resolve()
    rel = name.removeprefix("file://")
    tries = [folder / rel, root / rel]
    if name.startswith("package://"):
        pkg, _, rest = name.removeprefix("package://").partition("/")
        tries = [folder / rest, root / rest, folder / pkg / rest, root / pkg / rest]
    for p in tries:
        try:
            r = p.resolve()
        except RuntimeError:  # a link loop: not a mesh file
            continue
        if (root == r or root in r.parents) and p.is_file():
            return p
    raise UserError(f"{where}: mesh {name!r} not found under {root} (looked for {tries[0]}); copy it there")


def _geometry(urdf: Path, geom: ET.Element | None, where: str, root: Path | None) -> list[trimesh.Trimesh]:
    """The visual's meshes in its own frame (m, scale applied), each with the look its file gives."""
    shape = None if geom is None else next(iter(geom), None)
    if shape is None:
        raise UserError(f"{where}: a visual without geometry")
    if shape.tag == "box":
        return [trimesh.creation.box(_floats(shape.get("size"), 3, np.nan, where))]
    if shape.tag == "cylinder":
        r, h = _floats(shape.get("radius"), 1, np.nan, where)[0], _floats(shape.get("length"), 1, np.nan, where)[0]
        return [trimesh.creation.cylinder(radius=r, height=h, sections=64)]
    if shape.tag == "sphere":
        return [trimesh.creation.icosphere(subdivisions=4, radius=_floats(shape.get("radius"), 1, np.nan, where)[0])]
    if shape.tag != "mesh" or not shape.get("filename"):
        raise UserError(f"{where}: geometry <{shape.tag}> is not a mesh, box, cylinder or sphere")
    path = _mesh_path(urdf, shape.get("filename"), where, root)
    check_file(path)
    if path.suffix.lower() in (".urdf", ".step", ".stp"):
        raise UserError(f"{where}: a link's mesh must be STL, OBJ, PLY, GLB or GLTF, not {path.name}")
    part = meshfile.read(path)
    scale = _floats(shape.get("scale"), 3, 1.0, where)
    out = []
    if part.surface is not None:  # keep the look: the surface's vertices are the mesh's, unshared where baked
        s = part.surface
        m = trimesh.Trimesh(s.vertices * scale, s.faces, process=False,
                            visual=trimesh.visual.TextureVisuals(uv=s.uv, image=_pil(s.image)))
        out.append(m)
    else:
        m = trimesh.Trimesh(np.asarray(part.mesh.vertices) * scale, part.mesh.faces, process=False)
        if part.rgba is not None:
            m.visual.face_colors = np.round(np.asarray(part.rgba) * 255).astype(np.uint8)
        out.append(m)
    return out


def _pil(image: np.ndarray):
    from PIL import Image

    return Image.fromarray(image, "RGB")


def _colour(mat: ET.Element | None, named: dict[str, np.ndarray], where: str) -> np.ndarray | None:
    """The visual's material colour, RGBA uint8, or None when it names none."""
    if mat is None:
        return None
    c = mat.find("color")
    if c is not None:
        rgba = _floats(c.get("rgba"), 4, np.nan, where)
        return np.round(np.clip(rgba, 0.0, 1.0) * 255).astype(np.uint8)
    return named.get(mat.get("name", ""))


def _link_poses(robot: ET.Element, where: str) -> dict[str, np.ndarray]:
    """Each link's pose in the root link's frame with every joint at zero."""
    links = [ln.get("name") for ln in robot.findall("link")]
    children: dict[str, list[tuple[str, np.ndarray]]] = {}
    is_child = set()
    for j in robot.findall("joint"):
        parent, child = j.find("parent"), j.find("child")
        if parent is None or child is None:
            raise UserError(f"{where}: joint {j.get('name')!r} lacks a parent or child link")
        children.setdefault(parent.get("link"), []).append(
            (child.get("link"), _origin(j.find("origin"), f"{where}: joint {j.get('name')!r} origin")))
        is_child.add(child.get("link"))
    roots = [ln for ln in links if ln not in is_child]
    if len(roots) != 1:
        raise UserError(f"{where}: needs one root link (a link no joint moves), found {len(roots)}")
    poses, todo = {roots[0]: np.eye(4)}, [roots[0]]
    while todo:
        p = todo.pop()
        for c, T in children.get(p, []):
            if c in poses:
                raise UserError(f"{where}: the joints form a loop at link {c!r}")
            poses[c] = poses[p] @ T
            todo.append(c)
    return poses


def read(path: Path, mesh_root: Path | None = None) -> Part:
    """The part a URDF describes (m): its links' visuals (or, without any, collision shapes) in one mesh, in the root
    link's frame; its meshes found under ``mesh_root`` (None: the URDF's package; ``_mesh_path``)."""
    try:
        robot = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise UserError(f"{path}: not valid XML ({e})") from None
    if robot.tag != "robot":
        raise UserError(f"{path}: not a URDF (its root element is <{robot.tag}>, not <robot>)")
    named = {m.get("name"): c for m in robot.findall("material")
             if (c := _colour(m, {}, f"{path}: material {m.get('name')!r}")) is not None}
    poses = _link_poses(robot, str(path))
    meshes, looks, notes = [], [], ()
    kind = "visual" if robot.findall("link/visual") else "collision"
    if kind == "collision":
        notes += (f"{path.name} has no visual geometry: its collision geometry is the part's shape",)
    for link in robot.findall("link"):
        for vis in link.findall(kind):
            where = f"{path}: link {link.get('name')!r}"
            T = poses.get(link.get("name"), np.eye(4)) @ _origin(vis.find("origin"), f"{where} {kind} origin")
            colour = _colour(vis.find("material"), named, where)
            shape = vis.find("geometry/mesh")
            if colour is None and shape is not None and shape.get("filename"):  # the mesh file's look is used
                notes += meshfile.unread_materials(_mesh_path(path, shape.get("filename"), where, mesh_root))
            for m in _geometry(path, vis.find("geometry"), where, mesh_root):
                m.apply_transform(T)
                meshes.append(m)
                looks.append(colour if colour is not None else meshfile.look(m))
    if not meshes:
        raise UserError(f"{path}: no link has a visual or collision geometry")
    return dataclasses.replace(meshfile.combined(meshes, looks), notes=notes)
