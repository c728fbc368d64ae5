"""The object-set folder: BOP models plus one simulator file per object (format in ``docs/objects.md``).

    SET/objectset.json             the manifest: format, version, the objects' ids, names and files
    SET/models/obj_NNNNNN.ply      BOP models: binary PLY, millimetres, vertex normals
    SET/models/models_info.json    BOP: diameter, min_x/y/z, size_x/y/z, symmetries (mm)
    SET/objects/obj_NNNNNN.json    the simulator's part, SI units: mass, density, friction, colour, collision
                                   pieces, upright resting face, and where the model came from
    SET/objects/obj_NNNNNN_surface.ply, obj_NNNNNN_texture.png
                                   only for a part with a texture or several colours, or a remeshed part drawn
                                   with its input surface: the surface it is drawn with (``posegrasp.surface``),
                                   named by the json's ``surface`` entry

Everything here is in SI units (m, kg) in the OBJECT frame: origin at the centre of the model's bounding box.
The set is written in a temporary folder beside ``SET`` and renamed into place, so a failed or killed import
leaves no partial set; the same objects give byte-identical files. ``load_object_set`` checks every file.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from posegrasp import inputs
from posegrasp.bop import load_models_info
from posegrasp.bop.models import model_arrays
from posegrasp.errors import DatasetError, UserError
from posegrasp.geometry import quat_to_R
from posegrasp.io import dumps_json
from posegrasp.surface import TexturedSurface, read_surface

MANIFEST = "objectset.json"
FORMAT = "posegrasp object set"
VERSION = 1
_MM = 1e-3


@dataclass(frozen=True, eq=False)
class SetObject:
    """One object of a set, in metres and kilograms, in its object frame.

    Attributes:
        obj_id: BOP object id (1-based, consecutive in a set).
        name: Unique name within the set.
        vertices, faces: (N, 3) vertices (m) and (M, 3) outward triangles of the model.
        mass: Mass (kg); density (kg/m^3) times the model's volume.
        density: Density (kg/m^3).
        friction: MuJoCo geom friction (sliding, torsional, rolling).
        rgba: Display colour.
        collision: Convex pieces as ``{"type": "mesh", "vertices": [[x, y, z], ...]}`` (m; MuJoCo collides a
            mesh geom as its convex hull), or the primitives ``box``/``cylinder`` of the block catalogue.
        upright_quat: (w, x, y, z) of ``R_table_obj``: the object standing on its upright resting face on the
            table, in the kit's yaw.
        upright_down: (3,) unit outward normal of that face (object frame): ``R_table_obj @ upright_down = -z``.
        flat_top, flat_bottom: standing upright, is its top a flat face a part can stand on, and does its bottom
            rest flat (which pairs can stack; as the block catalogue's ``upright`` entry).
        diameter: Largest distance between two surface points (m).
        min_xyz, extents: Bounding-box corner and size (m).
        symmetries_discrete: 4x4 transforms (m) mapping the model onto itself, identity excluded.
        symmetries_continuous: ``(axis, offset m)``: any rotation about that line maps the model onto itself.
        collision_volume_ratio: Volume of the pieces' union over the model's.
        source: Where it came from: ``file``, ``unit``, ``scale`` and ``offset`` (``v_obj = v_file * scale +
            offset``, m), ``symmetries`` ("found" or the models_info.json they were taken from).
        repairs: What the import repaired, in words.
        volume_change: The repaired model's volume over the input surface's, minus 1 (0 when nothing was repaired).
        warnings: How the object does not suit the workcell, and what of its file the import could not use, in
            words (empty when neither).
        surface: The textured surface (m, object frame) it is drawn with, where one colour (``rgba``, then white)
            does not say how it looks or the model was remeshed (its input surface, in one colour); None draws
            the model in ``rgba``.
    """

    obj_id: int
    name: str
    vertices: np.ndarray
    faces: np.ndarray
    mass: float
    density: float
    friction: tuple[float, float, float]
    rgba: tuple[float, float, float, float]
    collision: tuple[dict[str, Any], ...]
    upright_quat: tuple[float, float, float, float]
    upright_down: np.ndarray
    flat_top: bool
    flat_bottom: bool
    diameter: float
    min_xyz: np.ndarray
    extents: np.ndarray
    symmetries_discrete: tuple[np.ndarray, ...] = ()
    symmetries_continuous: tuple[tuple[np.ndarray, np.ndarray], ...] = ()
    collision_volume_ratio: float = 1.0
    source: dict[str, Any] = field(default_factory=dict)
    repairs: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    surface: TexturedSurface | None = None
    volume_change: float = 0.0

    @property
    def volume(self) -> float:
        """Model volume (m^3)."""
        return self.mass / self.density


@dataclass(frozen=True)
class ObjectSet:
    """A loaded object set: its folder and its objects, ordered by ``obj_id``."""

    root: Path
    objects: tuple[SetObject, ...]
    firm_hold_tasks: tuple[str, ...] | None = None  # the trial tasks that hold these objects firmly (the
    # manifest's ``firm_hold_tasks``; None where it names none: the trials' own default)

    def by_name(self) -> dict[str, SetObject]:
        """The objects keyed by name, in ``obj_id`` order."""
        return {o.name: o for o in self.objects}


# ----------------------------------------------------------------------------- writing


def _r(x: Any, nd: int) -> Any:
    """Floats (nested lists/arrays) rounded to ``nd`` decimals, without negative zeros."""
    return (np.round(np.asarray(x, np.float64), nd) + 0.0).tolist()


def _ply_bytes(vertices_m: np.ndarray, faces: np.ndarray) -> bytes:
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices_m) / _MM, np.asarray(faces), process=False)
    return trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=True)


def _models_info(o: SetObject) -> dict[str, Any]:
    lo, size = np.asarray(o.min_xyz) / _MM, np.asarray(o.extents) / _MM
    disc = []
    for T in o.symmetries_discrete:
        T = np.array(T, np.float64)
        T[:3, 3] /= _MM
        disc.append(_r(T.reshape(-1), 9))
    return {"diameter": _r(o.diameter / _MM, 6),
            "min_x": _r(lo[0], 6), "min_y": _r(lo[1], 6), "min_z": _r(lo[2], 6),
            "size_x": _r(size[0], 6), "size_y": _r(size[1], 6), "size_z": _r(size[2], 6),
            "symmetries_discrete": disc,
            "symmetries_continuous": [{"axis": _r(a, 9), "offset": _r(np.asarray(c) / _MM, 6)}
                                      for a, c in o.symmetries_continuous]}


def _piece(p: dict[str, Any]) -> dict[str, Any]:
    if p["type"] == "mesh":
        return {"type": "mesh", "vertices": _r(p["vertices"], 9)}
    return {k: (_r(v, 9) if k != "type" else v) for k, v in p.items()}


def _object_json(o: SetObject) -> dict[str, Any]:
    return {
        "obj_id": o.obj_id, "name": o.name, "model": f"models/obj_{o.obj_id:06d}.ply",
        "mass_kg": _r(o.mass, 9), "density": _r(o.density, 6), "volume_m3": _r(o.volume, 12),
        "friction": _r(o.friction, 9), "rgba": _r(o.rgba, 6),
        "upright": {"down": _r(o.upright_down, 9), "quat": _r(o.upright_quat, 9), "flat_top": bool(o.flat_top),
                    "flat_bottom": bool(o.flat_bottom)},
        "collision": [_piece(p) for p in o.collision],
        "collision_volume_ratio": _r(o.collision_volume_ratio, 4),
        "source": o.source, "repairs": list(o.repairs), "warnings": list(o.warnings),
        **({} if o.surface is None else {"surface": {"mesh": f"objects/{_surface_names(o.obj_id)[0]}",
                                                     "texture": f"objects/{_surface_names(o.obj_id)[1]}"}}),
    }


def _surface_names(obj_id: int) -> tuple[str, str]:
    return f"obj_{obj_id:06d}_surface.ply", f"obj_{obj_id:06d}_texture.png"


def set_files(objects: list[SetObject], firm_hold_tasks: tuple[str, ...] | None = None) -> dict[str, bytes]:
    """Every file of a set holding ``objects`` (relative path -> bytes); ``firm_hold_tasks`` goes into the
    manifest when given."""
    if [o.obj_id for o in objects] != list(range(1, len(objects) + 1)):
        raise ValueError("object ids must run 1, 2, ... in order")
    files = {f"models/obj_{o.obj_id:06d}.ply": _ply_bytes(o.vertices, o.faces) for o in objects}
    text = {"models/models_info.json": {str(o.obj_id): _models_info(o) for o in objects}}
    for o in objects:
        text[f"objects/obj_{o.obj_id:06d}.json"] = _object_json(o)
        if o.surface is not None:
            mesh, tex = _surface_names(o.obj_id)
            files[f"objects/{mesh}"], files[f"objects/{tex}"] = o.surface.ply(), o.surface.png()
    text[MANIFEST] = {
        "format": FORMAT, "version": VERSION,
        "units": "objects/*.json in SI units (m, kg); models/ in BOP's millimetres",
        "frame": "origin at the centre of each model's bounding box",
        "objects": [{"obj_id": o.obj_id, "name": o.name, "file": f"objects/obj_{o.obj_id:06d}.json",
                     **({"repairs": list(o.repairs), "volume_change": _r(o.volume_change, 6)} if o.repairs else {})}
                    for o in objects]}
    if firm_hold_tasks is not None:
        text[MANIFEST]["firm_hold_tasks"] = list(firm_hold_tasks)
    files.update({k: (dumps_json(v) + "\n").encode() for k, v in text.items()})
    return dict(sorted(files.items()))


def check_writable_set(out: Path) -> None:
    """Refuse ``out`` when it is something other than a new or empty folder or an existing object set."""
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / MANIFEST).is_file())):
        raise UserError(f"--out {out} exists and is not an object set; name a new folder (nothing was replaced)")


def write_object_set(out: Path, objects: list[SetObject], firm_hold_tasks: tuple[str, ...] | None = None) -> Path:
    """Write the set atomically: built in a temporary folder beside ``out``, then renamed to ``out`` (an earlier
    set there is replaced only once the new one is complete)."""
    out = Path(out)
    check_writable_set(out)
    files = set_files(objects, firm_hold_tasks)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    old = None
    try:
        for rel, data in files.items():
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            with open(tmp / rel, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
        os.chmod(tmp, 0o755)
        if out.exists():
            old = out.parent / f"{tmp.name}.old"
            os.replace(out, old)
        os.replace(tmp, out)
    except BaseException:
        if old is not None and old.exists() and not out.exists():
            os.replace(old, out)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return out


# ----------------------------------------------------------------------------- reading


def _read(path: Path, what: str) -> dict[str, Any]:
    """The JSON object in the set's file ``path`` (UTF-8; a NaN is refused by the key's own check); a one-line
    DatasetError if not."""
    if not os.path.lexists(path):
        raise DatasetError(f"object set file {path} is missing ({what}); re-import the set")
    d = inputs.read_json(path, DatasetError, finite=False)
    bad = inputs.nonfinite(d)
    if bad:
        raise DatasetError(f"{path}: {bad[0]} = {json.dumps(bad[1])} is not a finite number; re-import the set")
    if not isinstance(d, dict):
        raise DatasetError(f"object set file {path}: expected a JSON object, got {type(d).__name__}; "
                           "re-import the set")
    return d


def _not_a_set(root: Path) -> DatasetError:
    if (root / "models").is_dir() and ((root / "camera.json").is_file() or any(root.glob("train*"))):
        return DatasetError(f"{root} is a BOP dataset, not an object set; make one from its models with "
                            f"`posegrasp objects import {root / 'models'} --out SET`")
    return UserError(f"{root} is not an object set (no {MANIFEST}); make one with `posegrasp objects import`")


#: The numbers of an object file: key -> (count, 0 for a single number; lowest; highest value).
OBJECT_NUMBERS = {"mass_kg": (0, 1e-6, 1e4), "density": (0, 1.0, 25000.0), "friction": (3, 0.0, 10.0),
                  "rgba": (4, 0.0, 1.0)}


def _check_numbers(where: Path, key: str, value: Any, n: int, lo: float, hi: float) -> None:
    """A one-line DatasetError unless ``value`` is a finite number (``n`` = 0) or a list of ``n`` of them, each in
    [lo, hi]."""
    values = value if n and isinstance(value, list) and len(value) == n else [value] if not n else None
    ok = values is not None and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                                    and lo <= v <= hi for v in values)
    if not ok:
        what = "a number" if not n else f"a list of {n} numbers"
        raise DatasetError(f"{where}: {key} = {json.dumps(value)[:60]} is not {what} in [{lo:g}, {hi:g}]; "
                           "re-import the set")


def _in_set(root: Path, rel: Any, where: Path | str) -> Path:
    """The file ``rel`` (a path relative to the set folder ``root``, as the set's files name theirs); a DatasetError
    naming ``where`` if it is not a relative path inside the set (absolute, climbing out, or through a link out)."""
    path = root / str(rel)
    try:
        inside = isinstance(rel, str) and not Path(rel).is_absolute() and root.resolve() in path.resolve().parents
    except RuntimeError:  # a link loop: the reader names it
        return path
    if not inside:
        raise DatasetError(f"{where}: {rel!r} is not a file inside the set folder {root}; re-import the set")
    return path


def _parse_object(root: Path, entry: dict[str, Any], info: dict[int, Any]) -> SetObject:
    oid, name = int(entry["obj_id"]), str(entry["name"])
    where = _in_set(root, entry["file"], root / MANIFEST)
    d = _read(where, f"object {name}")
    if d.get("obj_id") != oid or d.get("name") != name:
        raise DatasetError(f"{where} says obj_id {d.get('obj_id')} {d.get('name')!r}, the manifest {oid} {name!r}; "
                           "re-import the set")
    if oid not in info:
        raise DatasetError(f"{root / 'models/models_info.json'} has no entry for obj_id {oid}; re-import the set")
    vertices, faces = model_arrays(_in_set(root, d["model"], where))
    mi = info[oid]
    used = vertices[np.unique(faces)]  # the bounds of the faces, as trimesh's
    least, size = used.min(axis=0), np.ptp(used, axis=0)
    if np.abs(least - mi.min_xyz).max() > 1e-5 or np.abs(size - mi.size_xyz).max() > 1e-5:
        raise DatasetError(f"{root / d['model']} does not match its models_info.json entry (bounding box); "
                           "re-import the set")
    for key, (n, lo, hi) in OBJECT_NUMBERS.items():
        _check_numbers(where, key, d.get(key), n, lo, hi)
    if "collision_volume_ratio" in d:  # written by the importer since it decomposes shapes
        _check_numbers(where, "collision_volume_ratio", d["collision_volume_ratio"], 0, 1e-6, 1e3)
    pieces = tuple(d["collision"])
    if not pieces:
        raise DatasetError(f"{where}: needs at least one collision piece; re-import the set")
    surface = None
    if "surface" in d:
        ply, tex = (_in_set(root, d["surface"][k], where) for k in ("mesh", "texture"))
        for f in (ply, tex):
            if not os.path.lexists(f):
                raise DatasetError(f"object set file {f} is missing (the surface of {name}); re-import the set")
        data = [inputs.read_bytes(f, kind, DatasetError) for f, kind in ((ply, "mesh"), (tex, "image"))]
        inputs.check_image_header(data[1], str(tex), DatasetError)
        try:
            surface = read_surface(*data)
        except Exception as e:  # PIL and numpy raise many types on damaged files
            raise DatasetError(f"{ply} or {tex.name} is damaged ({e}); re-import the set") from None
    up = d["upright"]
    quat, down = np.asarray(up["quat"], np.float64), np.asarray(up["down"], np.float64)
    if abs(np.linalg.norm(quat) - 1.0) > 1e-6 or np.abs(quat_to_R(quat) @ down - [0.0, 0.0, -1.0]).max() > 1e-6:
        raise DatasetError(f"{where}: upright.quat {quat.tolist()} is not a unit quaternion turning upright.down "
                           f"{down.tolist()} to -z; re-import the set")
    return SetObject(
        obj_id=oid, name=name, vertices=vertices, faces=faces,
        mass=float(d["mass_kg"]), density=float(d["density"]), friction=tuple(d["friction"]),
        rgba=tuple(d["rgba"]), collision=pieces, upright_quat=tuple(quat.tolist()), upright_down=down,
        flat_top=bool(up.get("flat_top", False)), flat_bottom=bool(up.get("flat_bottom", False)),
        diameter=mi.diameter, min_xyz=mi.min_xyz, extents=mi.size_xyz,
        symmetries_discrete=tuple(mi.symmetries_discrete),
        symmetries_continuous=tuple((a / np.linalg.norm(a), c) for a, c in mi.symmetries_continuous),
        collision_volume_ratio=float(d.get("collision_volume_ratio", 1.0)), source=d.get("source", {}),
        repairs=tuple(d.get("repairs", ())), warnings=tuple(d.get("warnings", ())), surface=surface,
        volume_change=float(entry.get("volume_change", 0.0)))


def load_object_set(root: str | Path) -> ObjectSet:
    """The object set in folder ``root``, every file checked (a one-line ``DatasetError`` naming the bad one)."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"object set {root} does not exist (or is not a folder)")
    if not os.path.lexists(root / MANIFEST):
        raise _not_a_set(root)
    man = _read(root / MANIFEST, "the manifest")
    if man.get("format") != FORMAT or man.get("version") != VERSION or type(man.get("version")) is not int:
        raise DatasetError(f"{root / MANIFEST}: format {man.get('format')!r} version {man.get('version')!r} is not "
                           f"{FORMAT!r} version {VERSION}; re-import the set")
    entries = man.get("objects") or []
    if not isinstance(entries, list) or not all(
            isinstance(e, dict) and {"obj_id", "name", "file"} <= set(e) and type(e["obj_id"]) is int
            and isinstance(e["name"], str) and isinstance(e["file"], str) for e in entries):
        raise DatasetError(f"{root / MANIFEST}: objects must be a list, each with an integer obj_id, a name and a "
                           "file; re-import the set")
    if [int(e["obj_id"]) for e in entries] != list(range(1, len(entries) + 1)):
        raise DatasetError(f"{root / MANIFEST}: obj_ids must run 1, 2, ... in order; re-import the set")
    if len({e["name"] for e in entries}) != len(entries):
        raise DatasetError(f"{root / MANIFEST}: object names must be unique; re-import the set")
    hold = man.get("firm_hold_tasks")
    if hold is not None and not (isinstance(hold, list) and all(isinstance(t, str) for t in hold)):
        raise DatasetError(f"{root / MANIFEST}: firm_hold_tasks must be a list of task names, not {hold!r}; "
                           "re-import the set")
    info = load_models_info(root / "models" / "models_info.json")
    try:
        return ObjectSet(root=root, objects=tuple(_parse_object(root, e, info) for e in entries),
                         firm_hold_tasks=None if hold is None else tuple(hold))
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"object set {root} has a malformed file ({type(e).__name__}: {e}); re-import it") from None
