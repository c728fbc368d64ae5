"""BOP writers and readers only the tests need: models, ``models_info.json``, depth and mask PNGs written
one file at a time, and the results CSV read back. Metres in, millimetres on disk, as ``posegrasp.bop``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from posegrasp import bop
from posegrasp.bop import results as bop_results
from posegrasp.bop import images as bop_images
from posegrasp import io as pio
from posegrasp.bop import MM


def write_models_info(root: str | Path, infos: dict[int, bop.ObjectInfo]) -> Path:
    """Write ``<root>/models/models_info.json`` (values converted to mm)."""
    out = {}
    for oid, inf in sorted(infos.items()):
        d: dict[str, Any] = {"diameter": inf.diameter / MM}
        for ax, lo, sz in zip("xyz", inf.min_xyz, inf.size_xyz):
            d[f"min_{ax}"], d[f"size_{ax}"] = float(lo) / MM, float(sz) / MM
        if inf.symmetries_discrete:
            mats = []
            for s in inf.symmetries_discrete:
                s = np.array(s, dtype=np.float64)
                s[:3, 3] /= MM
                mats.append(s.reshape(-1).tolist())
            d["symmetries_discrete"] = mats
        if inf.symmetries_continuous:
            d["symmetries_continuous"] = [{"axis": np.asarray(a, float).tolist(),
                                           "offset": (np.asarray(o, float) / MM).tolist()}
                                          for a, o in inf.symmetries_continuous]
        out[str(oid)] = d
    return pio.write_json(bop.models_info_path(root), out)


def object_info_from_mesh(obj_id: int, mesh, symmetries_discrete: list[np.ndarray] | None = None,
                          symmetries_continuous: list[tuple[np.ndarray, np.ndarray]] | None = None) -> bop.ObjectInfo:
    """ObjectInfo (m) of a mesh in metres: diameter = largest vertex distance, bounding box."""
    from scipy.spatial.distance import pdist

    v = np.asarray(mesh.vertices, dtype=np.float64)
    if len(v) > 2000:
        import trimesh

        v = np.asarray(trimesh.convex.convex_hull(mesh).vertices)
    lo, hi = v.min(axis=0), v.max(axis=0)
    return bop.ObjectInfo(obj_id=obj_id, diameter=float(pdist(v).max()), min_xyz=lo, size_xyz=hi - lo,
                          symmetries_discrete=list(symmetries_discrete or []),
                          symmetries_continuous=list(symmetries_continuous or []))


def write_model_ply(root: str | Path, obj_id: int, mesh) -> Path:
    """Write a trimesh model given in metres to ``<root>/models/obj_XXXXXX.ply`` in mm (binary PLY)."""
    m = mesh.copy()
    m.apply_scale(1.0 / MM)
    return pio.write_bytes(bop.model_path(root, obj_id), m.export(file_type="ply"))


def write_depth(path: str | Path, depth_m: np.ndarray, depth_scale: float = 1.0) -> Path:
    """Atomically write a depth map in metres as a BOP uint16 png."""
    return pio.write_image(path, bop_images.depth_to_png(depth_m, depth_scale))


def write_mask(path: str | Path, mask: np.ndarray) -> Path:
    """Atomically write a boolean mask as a 0/255 png."""
    return pio.write_image(path, np.asarray(mask, dtype=bool).astype(np.uint8) * 255)


#: Reading a BOP results CSV back (translations to metres).
read_results_csv = bop_results.read_results_csv
