"""The object catalogue: any object set's meshes, masses, collision pieces, upright faces and symmetries.

An object set (``posegrasp.objset``, format in ``docs/objects.md``) is a folder of BOP models plus one
simulator file per object; the shipped default is the eight building blocks in ``assets/blocks`` (written by
``assets/blocks/make_blocks.py``). Every command that builds scenes names its set with ``--objects SET``
(``WorkcellConfig.objects``: ``""`` is the shipped set) and reads it through ``load_catalog``.

Everything returned here is in SI units (metres, kilograms) and in the OBJECT frame: origin at the
centre of the object's axis-aligned bounding box. The files on disk follow BOP: models and
``models_info.json`` in millimetres.
"""

from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from posegrasp import ASSETS, inputs
from posegrasp.errors import DatasetError
from posegrasp.geometry import axis_angle_R, make_T
from posegrasp.objset import MANIFEST, ObjectSet, SetObject, load_object_set
from posegrasp.surface import TexturedSurface

#: The shipped object set, used when ``objects`` is empty.
DEFAULT_SET = ASSETS / "blocks"


@dataclass(frozen=True, eq=False)
class PartType:
    """One object type of a set, in metres, in its object frame (compared and hashed by identity; read-only
    arrays).

    Attributes:
        obj_id: BOP object id (1-based).
        name: Unique name within its set.
        vertices: (N, 3) mesh vertices (m).
        faces: (M, 3) triangle vertex indices, outward-facing (counter-clockwise seen from outside).
        mass: Mass (kg), density times the mesh volume.
        collision: MuJoCo pieces (m) approximating the solid, as in the set's ``objects/*.json``:
            ``{"type": "box", "size": half-sizes, "pos", "quat" (w, x, y, z)}``,
            ``{"type": "cylinder", "size": [radius, half_height], "pos", "quat"}`` (axis local z) or
            ``{"type": "mesh", "vertices": [[x, y, z], ...]}`` (one convex piece).
        diameter: Largest distance between two vertices (m).
        extents: (3,) bounding-box size along x, y, z (m).
        symmetries_discrete: 4x4 transforms (m) mapping the object onto itself, identity excluded.
        symmetries_continuous: ``(axis (3,), offset (3,) m)``: rotation by any angle about the line
            through ``offset`` along ``axis`` maps the object onto itself.
        friction: MuJoCo geom friction hint (sliding, torsional, rolling).
        rgba: Display colour.
        upright_down: (3,) unit object-frame direction that points straight down when the object stands
            upright (a brick studs up, an arch on its feet), or None if the type has no upright pose.
        upright_quat: (w, x, y, z) of ``R_table_obj`` standing it upright at the kit's yaw
            (``R_table_obj @ upright_down = -z``).
        flat_top, flat_bottom: standing upright, is its top one flat face another object can stand on, and
            does its bottom rest flat on such a face (which pairs can stack)?
        surface: The textured surface (m, object frame) the object is drawn with, where its set
            gives a texture or several colours; None: drawn as ``vertices``/``faces`` in one colour.
    """

    obj_id: int
    name: str
    vertices: np.ndarray
    faces: np.ndarray
    mass: float
    collision: tuple[dict[str, Any], ...]
    diameter: float
    extents: np.ndarray
    symmetries_discrete: tuple[np.ndarray, ...]
    symmetries_continuous: tuple[tuple[np.ndarray, np.ndarray], ...]
    friction: tuple[float, float, float] = (0.5, 0.005, 0.0001)
    rgba: tuple[float, float, float, float] = field(default=(0.8, 0.8, 0.8, 1.0))
    upright_down: np.ndarray | None = None
    upright_quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    flat_top: bool = False
    flat_bottom: bool = False
    surface: TexturedSurface | None = None


#: The former name of ``PartType``, kept so plug-ins written against it still import.
BlockType = PartType


def _frozen(a: Any, dtype: Any = np.float64) -> np.ndarray:
    out = np.array(a, dtype=dtype)
    out.flags.writeable = False
    return out


def set_root(objects: str | Path | None = "") -> Path:
    """The folder of the object set ``objects`` names (absolute): the shipped set for ``""`` or None."""
    return DEFAULT_SET if objects in ("", None) else Path(objects).expanduser().resolve()


def _block(o: SetObject) -> PartType:
    """A ``PartType`` from a ``SetObject`` (the file's rounded rotations made orthonormal again)."""
    disc = []
    for T in o.symmetries_discrete:
        T = np.array(T, np.float64)
        U, _, Vt = np.linalg.svd(T[:3, :3])  # undo the rounding in the file: nearest rotation
        T[:3, :3] = U @ Vt
        disc.append(_frozen(T))
    down = np.asarray(o.upright_down, float)
    return PartType(
        obj_id=o.obj_id, name=o.name, vertices=_frozen(o.vertices), faces=_frozen(o.faces, np.int64), mass=o.mass,
        collision=o.collision, diameter=o.diameter, extents=_frozen(o.extents), symmetries_discrete=tuple(disc),
        symmetries_continuous=tuple((_frozen(a), _frozen(c)) for a, c in o.symmetries_continuous),
        friction=tuple(o.friction), rgba=tuple(o.rgba), upright_down=_frozen(down / np.linalg.norm(down)),
        upright_quat=tuple(o.upright_quat), flat_top=o.flat_top, flat_bottom=o.flat_bottom,
        surface=o.surface)


@functools.lru_cache(maxsize=8)
def _set(root: Path) -> ObjectSet:
    return load_object_set(root)


@functools.lru_cache(maxsize=8)
def _load(root: Path) -> tuple[PartType, ...]:
    return tuple(_block(o) for o in _set(root).objects)


def set_firm_hold_tasks(objects: str | Path | None = "") -> tuple[str, ...] | None:
    """The trial tasks the object set ``objects`` asks to hold its objects firmly (None: it names none)."""
    return _set(set_root(objects)).firm_hold_tasks


def load_catalog(objects: str | Path | None = "") -> dict[str, PartType]:
    """Every object type of the set ``objects`` (a set folder; ``""``: the shipped blocks), keyed by name,
    ordered by ``obj_id`` (cached per folder).

    Raises:
        DatasetError: one line naming the folder or file, when it is no object set or a file of it is missing or
            inconsistent (``posegrasp.objset.load_object_set`` checks every file).
    """
    return {b.name: b for b in _load(set_root(objects))}


def catalog_by_id(objects: str | Path | None = "") -> dict[int, PartType]:
    """``load_catalog(objects)`` keyed by ``obj_id``."""
    return {b.obj_id: b for b in _load(set_root(objects))}


@functools.lru_cache(maxsize=8)
def _digest(root: Path) -> str:
    files = [MANIFEST, "models/models_info.json", *sorted(p.relative_to(root).as_posix() for d in ("objects", "models")
                                                          for p in (root / d).glob("obj_*"))]
    h = hashlib.sha256()
    for rel in files:
        h.update(rel.encode() + b"\0" + hashlib.sha256(inputs.read_bytes(root / rel, "mesh", DatasetError)).digest())
    return h.hexdigest()


def set_record(objects: str | Path | None = "") -> dict[str, str]:
    """What a run records of the object set it used: ``name`` (its folder's), ``path`` and ``sha256`` (of its
    manifest, object files and models: two runs used the same set when these are equal). Loads (checks) it."""
    root = set_root(objects)
    _load(root)
    return {"name": root.name, "path": str(root), "sha256": _digest(root)}


def symmetry_transforms(block: PartType, n_continuous: int = 36) -> np.ndarray:
    """(K, 4, 4) transforms ``T`` (m) with ``T``-moved block == block, identity first.

    Discrete symmetries plus identity; each continuous symmetry is sampled every ``360 / n_continuous``
    degrees about its axis (through its offset) and composed with every discrete one (``C @ D``,
    BOP's convention), so a cylinder gives ``2 * n_continuous`` transforms. With ``k`` continuous axes (a
    sphere's) each is sampled ``n_continuous ** (1 / k)`` times (at least twice), so that together they give
    about ``n_continuous`` transforms, not ``n_continuous ** k``.
    """
    out = [np.eye(4)] + [np.array(T) for T in block.symmetries_discrete]
    n = max(2, round(n_continuous ** (1.0 / max(1, len(block.symmetries_continuous)))))
    for axis, offset in block.symmetries_continuous:
        conts = []
        for k in range(n):
            R = axis_angle_R(axis, 2.0 * np.pi * k / n)
            conts.append(make_T(R, offset - R @ offset))
        out = [C @ D for C in conts for D in out]
    return np.stack(out)


def sample_surface(block: PartType, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points (m, object frame) drawn uniformly over the block's surface; same seed, same points."""
    rng = np.random.default_rng(seed)
    tri = block.vertices[block.faces]  # (M, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    idx = rng.choice(len(tri), size=n, p=area / area.sum())
    u, v = rng.random((2, n))
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    t = tri[idx]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
