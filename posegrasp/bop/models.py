"""A BOP dataset's object models: read (PLY, mm) into metres, sampled, and resampled densely for ``models_eval``."""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from posegrasp import inputs
from posegrasp.bop import MM, model_path
from posegrasp.bop.schema import MAX_MM
from posegrasp.errors import DatasetFileError


def load_model(root_or_file: str | Path, obj_id: int | None = None):
    """A model PLY (mm) as a ``trimesh.Trimesh`` in metres, of ``model_arrays``' vertices and triangles (the file's
    normals and colours left out); pass the dataset root and obj_id, or a file."""
    import trimesh

    return trimesh.Trimesh(*model_arrays(root_or_file, obj_id), process=False)


def model_arrays(root_or_file: str | Path, obj_id: int | None = None, scale: float = MM
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A model PLY's vertices (V, 3) (float64: the file's mm times ``scale``, metres by default) and triangles (F, 3)
    (int64); pass the dataset root and obj_id, or a file.

    ``DatasetFileError`` unless it is a triangle mesh with finite vertices, within ``bop_schema.MAX_MM`` of its
    origin and not flat to a point, whose faces index its vertices. A PLY laid out as this product and trimesh write
    models (``plain_ply``) is read without trimesh, as trimesh reads it."""
    p = _model_file(root_or_file, obj_id)
    data = inputs.read_bytes(p, "mesh", DatasetFileError)
    plain = plain_ply(data)
    if plain is None:
        mesh = _trimesh(p, data, scale)
        return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    _check(p, *plain)
    return plain[0] * scale + 0.0, plain[1]  # (+ 0.0: zeros positive, as trimesh's scaling leaves them)


#: Vertex property types ``plain_ply`` reads, as numpy little-endian types.
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
              "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
              "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}


def plain_ply(data: bytes) -> tuple[np.ndarray, np.ndarray] | None:
    """Vertices (V, 3) (float64, the file's units) and triangles (F, 3) (int64) of a binary little-endian PLY of
    two elements, ``vertex`` with scalar properties x, y, z among others and ``face`` with one list of uchar count
    and int indices, every face a triangle; None for any other file (trimesh reads those)."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        return None
    elements: list[tuple[str, int, list[list[str]]]] = []
    for line in data[4:end].decode("ascii", "replace").splitlines():
        w = line.split()
        if not w or w[0] == "comment" or w == ["format", "binary_little_endian", "1.0"]:
            continue
        if w[0] == "element" and len(w) == 3 and w[2].isdigit():
            elements.append((w[1], int(w[2]), []))
        elif w[0] == "property" and elements:
            elements[-1][2].append(w[1:])
        else:
            return None
    if [e[0] for e in elements] != ["vertex", "face"]:
        return None
    (_, nv, vprops), (_, nf, fprops) = elements
    if any(len(q) != 2 or q[0] not in _PLY_TYPES for q in vprops) or len(fprops) != 1 \
            or fprops[0][:3] not in (["list", "uchar", "int"], ["list", "uint8", "int32"]):
        return None
    vtype = np.dtype([(q[1], _PLY_TYPES[q[0]]) for q in vprops])
    ftype = np.dtype([("n", "u1"), ("i", "<i4", 3)])
    body = memoryview(data)[end + len(b"end_header\n"):]
    if not {"x", "y", "z"} <= set(vtype.names) or len(body) != nv * vtype.itemsize + nf * ftype.itemsize:
        return None
    v = np.frombuffer(body, vtype, nv)
    f = np.frombuffer(body, ftype, nf, offset=nv * vtype.itemsize)
    if (f["n"] != 3).any():
        return None
    return np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64), f["i"].astype(np.int64)


def _model_file(root_or_file: str | Path, obj_id: int | None) -> Path:
    p = model_path(root_or_file, obj_id) if obj_id is not None else Path(root_or_file)
    if not os.path.lexists(p):
        raise DatasetFileError(f"{p}: expected a PLY model (it does not exist)")
    return p


def _trimesh(p: Path, data: bytes, scale: float = MM):
    """The PLY bytes ``data`` (mm) of file ``p`` as a checked ``trimesh.Trimesh``, scaled by ``scale`` (metres)."""
    import trimesh

    try:
        mesh = trimesh.load(io.BytesIO(data), file_type="ply", force="mesh", process=False)
    except Exception as e:  # trimesh raises many types on corrupt files
        raise DatasetFileError(f"{p}: expected a PLY triangle mesh, got an unreadable file "
                               f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    _check(p, np.asarray(getattr(mesh, "vertices", np.zeros((0, 3)))),
           np.asarray(getattr(mesh, "faces", np.zeros((0, 3)))))
    if scale != 1:
        mesh.apply_scale(scale)
    return mesh


def _check(p: Path, v: np.ndarray, f: np.ndarray) -> None:
    """``load_model``'s checks of the vertices (V, 3) (mm) and faces (F, 3) read from ``p``."""
    if not len(f):
        raise DatasetFileError(f"{p}: expected a triangle mesh, got {len(v)} vertices and no faces")
    if not np.isfinite(v).all() or np.abs(v).max() > MAX_MM:
        raise DatasetFileError(f"{p}: expected finite vertices within {MAX_MM:g} mm of the origin")
    if f.min() < 0 or f.max() >= len(v):
        raise DatasetFileError(f"{p}: expected faces indexing its {len(v)} vertices")
    if not np.ptp(v, axis=0).max() > 0:
        raise DatasetFileError(f"{p}: expected a mesh with extent, got all vertices at one point")


def sample_model_points(mesh, n: int, seed: int = 0) -> np.ndarray:
    """n points (m) uniformly on the surface of a trimesh model, reproducible from ``seed``."""
    return sample_model_surface(mesh, n, seed)[0]


def sample_model_surface(mesh, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``sample_model_points``' n points (m) and the outward unit normals (n, 3) of the faces they lie on."""
    import trimesh

    pts, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts, dtype=np.float64), np.asarray(mesh.face_normals, dtype=np.float64)[face]


def unique_edges(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct edges (E, 2) of triangles f (F, 3), lower vertex first, ordered by their higher vertex, then their
    lower (as trimesh's ``edges_unique``), and each face's edges (F, 3): those of (f0, f1), (f1, f2), (f2, f0)."""
    e = np.sort(np.asarray(f, np.int64)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    key, inverse = np.unique((e[:, 1] << 32) | e[:, 0], return_inverse=True)
    return np.stack([key & 0xFFFFFFFF, key >> 32], axis=1), inverse.reshape(-1, 3)


def resample_for_eval(v: np.ndarray, f: np.ndarray, max_edge: float) -> tuple[np.ndarray, np.ndarray]:
    """The mesh of vertices v (V, 3) and triangles f (F, 3) with every edge longer than ``max_edge`` (v's units)
    split at its midpoint, repeatedly, each face re-triangulated by which of its edges were split (a conforming
    refinement: no T-junctions): the same surface with dense, roughly uniform vertices, like BOP's ``models_eval``.
    Returns its vertices (float64) and triangles (int64)."""
    v, f = np.asarray(v, np.float64), np.asarray(f, np.int64)
    while True:
        edges, fe = unique_edges(f)  # fe[:, k]: edge of (f[k], f[k + 1])
        long = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1) > max_edge
        if not long.any():
            return v, f
        mid = np.full(len(edges), -1)
        mid[long] = len(v) + np.arange(long.sum())
        v = np.concatenate([v, 0.5 * (v[edges[long, 0]] + v[edges[long, 1]])])
        local = np.concatenate([f, mid[fe]], axis=1)  # v0 v1 v2 m01 m12 m20 (-1: edge kept)
        code = (local[:, 3:] >= 0) @ np.array([4, 2, 1])
        f = np.concatenate([local[code == c][:, t].reshape(-1, 3) for c, t in _SPLIT_TRIANGLES.items()])


def ply_bytes(v: np.ndarray, f: np.ndarray) -> bytes:
    """A triangle mesh, vertices (V, 3) and triangles (F, 3), as binary PLY bytes: float32 x, y, z and int indices
    counted by a uchar, in the layout of trimesh's exporter, its comment line included (files written before
    match byte for byte)."""
    faces = np.empty(len(f), [("n", "u1"), ("i", "<i4", 3)])
    faces["n"], faces["i"] = 3, f
    header = (f"ply\nformat binary_little_endian 1.0\ncomment https://github.com/mikedh/trimesh\n"
              f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    return header.encode("ascii") + np.ascontiguousarray(v, "<f4").tobytes() + faces.tobytes()


#: Triangles (local vertex indices: 0-2 corners, 3-5 midpoints of edges 01, 12, 20) of a face whose split edges
#: are coded m01 * 4 + m12 * 2 + m20, fanned from a midpoint so that none is degenerate.
_SPLIT_TRIANGLES = {0: [0, 1, 2], 4: [3, 1, 2, 3, 2, 0], 2: [4, 2, 0, 4, 0, 1], 1: [5, 0, 1, 5, 1, 2],
                    6: [3, 1, 4, 3, 4, 2, 3, 2, 0], 3: [4, 2, 5, 4, 5, 0, 4, 0, 1], 5: [3, 1, 2, 3, 2, 5, 3, 5, 0],
                    7: [0, 3, 5, 3, 1, 4, 5, 4, 2, 3, 4, 5]}
