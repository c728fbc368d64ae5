"""The building-block catalogue: meshes, masses, collision primitives and symmetries.

Everything returned here is in SI units (metres, kilograms) and in the OBJECT frame: origin at the
centre of the block's axis-aligned bounding box, +z up in its natural resting pose, x along its
longest horizontal side. The files on disk (``assets/blocks``, written by
``assets/blocks/make_blocks.py``) follow BOP: models and ``models_info.json`` in millimetres.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from posegrasp import ASSETS
from posegrasp.errors import UserError
from posegrasp.geometry import axis_angle_R, make_T

_MM = 1e-3  # metres per millimetre


@dataclass(frozen=True, eq=False)
class BlockType:
    """One block type, in metres, in its object frame (compared and hashed by identity; read-only arrays).

    Attributes:
        obj_id: BOP object id (1-based).
        name: Unique name, e.g. ``"brick_2x4"``.
        vertices: (N, 3) mesh vertices (m).
        faces: (M, 3) triangle vertex indices, outward-facing (counter-clockwise seen from outside).
        mass: Mass (kg), ABS density times the mesh volume.
        collision: MuJoCo primitives (m) approximating the solid, as in ``catalog.json``:
            ``{"type": "box", "size": half-sizes, "pos", "quat" (w, x, y, z)}``,
            ``{"type": "cylinder", "size": [radius, half_height], "pos", "quat"}`` (axis local z) or
            ``{"type": "mesh", "vertices": [[x, y, z], ...]}`` (one convex piece).
        diameter: Largest distance between two vertices (m).
        extents: (3,) bounding-box size along x, y, z (m).
        symmetries_discrete: 4x4 transforms (m) mapping the block onto itself, identity excluded.
        symmetries_continuous: ``(axis (3,), offset (3,) m)``: rotation by any angle about the line
            through ``offset`` along ``axis`` maps the block onto itself.
        friction: MuJoCo geom friction hint (sliding, torsional, rolling).
        rgba: Display colour.
        upright_down: (3,) unit object-frame direction that points straight down when the block stands
            upright (studs up, an arch on its feet), or None if the type has no upright pose.
        flat_top, flat_bottom: standing upright, is its top one flat face another block can stand on, and
            does its bottom rest flat on such a face (which pairs can stack)?
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
    flat_top: bool = False
    flat_bottom: bool = False


def _frozen(a: Any, dtype: Any = np.float64) -> np.ndarray:
    out = np.array(a, dtype=dtype)
    out.flags.writeable = False
    return out


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"block catalogue file {path} is missing: run `python assets/blocks/make_blocks.py`") from None
    except json.JSONDecodeError as e:
        raise UserError(f"block catalogue file {path} is not valid JSON ({e}): regenerate it") from None


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    if not path.is_file():
        raise UserError(f"block model {path} is missing: run `python assets/blocks/make_blocks.py`")
    mesh = trimesh.load(path, process=False, force="mesh")
    return np.asarray(mesh.vertices, np.float64) * _MM, np.asarray(mesh.faces, np.int64)


def _upright(entry: dict | None) -> dict[str, Any]:
    """``BlockType`` upright fields from a catalogue entry's optional ``upright`` object."""
    if not entry:
        return {}
    down = np.asarray(entry["down"], float)
    return {"upright_down": _frozen(down / np.linalg.norm(down)), "flat_top": bool(entry.get("flat_top", False)),
            "flat_bottom": bool(entry.get("flat_bottom", False))}


@functools.lru_cache(maxsize=4)
def _load(root: Path) -> tuple[BlockType, ...]:
    catalog = _read_json(root / "catalog.json")
    info = _read_json(root / "models" / "models_info.json")
    blocks = []
    for entry in sorted(catalog["blocks"], key=lambda e: e["obj_id"]):
        oid = int(entry["obj_id"])
        if str(oid) not in info:
            raise UserError(f"{root / 'models' / 'models_info.json'} has no entry for obj_id {oid}: regenerate it")
        mi = info[str(oid)]
        vertices, faces = _read_ply(root / entry.get("model", f"models/obj_{oid:06d}.ply"))
        disc = []
        for flat in mi.get("symmetries_discrete", []):
            T = np.array(flat, np.float64).reshape(4, 4)
            U, _, Vt = np.linalg.svd(T[:3, :3])  # undo the rounding in the file: nearest rotation
            T[:3, :3] = U @ Vt
            T[:3, 3] *= _MM
            disc.append(_frozen(T))
        cont = tuple((_frozen(np.asarray(c["axis"], float) / np.linalg.norm(c["axis"])),
                      _frozen(np.asarray(c["offset"], float) * _MM))
                     for c in mi.get("symmetries_continuous", []))
        blocks.append(BlockType(
            obj_id=oid,
            name=str(entry["name"]),
            vertices=_frozen(vertices),
            faces=_frozen(faces, np.int64),
            mass=float(entry["mass_kg"]),
            collision=tuple(entry["collision"]),
            diameter=float(mi["diameter"]) * _MM,
            extents=_frozen([mi["size_x"] * _MM, mi["size_y"] * _MM, mi["size_z"] * _MM]),
            symmetries_discrete=tuple(disc),
            symmetries_continuous=cont,
            friction=tuple(entry.get("friction", (0.5, 0.005, 0.0001))),
            rgba=tuple(entry.get("rgba", (0.8, 0.8, 0.8, 1.0))),
            **_upright(entry.get("upright")),
        ))
    return tuple(blocks)


def load_catalog(root: Path = ASSETS / "blocks") -> dict[str, BlockType]:
    """All block types under ``root``, keyed by name, ordered by ``obj_id`` (cached per root).

    Raises:
        UserError: when a catalogue file is missing or unreadable.
    """
    return {b.name: b for b in _load(Path(root).resolve())}


def symmetry_transforms(block: BlockType, n_continuous: int = 36) -> np.ndarray:
    """(K, 4, 4) transforms ``T`` (m) with ``T``-moved block == block, identity first.

    Discrete symmetries plus identity; each continuous symmetry is sampled every ``360 / n_continuous``
    degrees about its axis (through its offset) and composed with every discrete one (``C @ D``,
    BOP's convention), so a cylinder gives ``2 * n_continuous`` transforms.
    """
    out = [np.eye(4)] + [np.array(T) for T in block.symmetries_discrete]
    for axis, offset in block.symmetries_continuous:
        conts = []
        for k in range(n_continuous):
            R = axis_angle_R(axis, 2.0 * np.pi * k / n_continuous)
            conts.append(make_T(R, offset - R @ offset))
        out = [C @ D for C in conts for D in out]
    return np.stack(out)


def sample_surface(block: BlockType, n: int, seed: int = 0) -> np.ndarray:
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
