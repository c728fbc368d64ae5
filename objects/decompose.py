"""Collision pieces: a convex decomposition of a solid with CoACD (MuJoCo collides each mesh as its convex hull).

A convex mesh is its own single piece (its hull). Otherwise CoACD (Wei et al. 2022) splits it until every piece's
concavity is below ``threshold`` (relative to the bounding box), merging down to at most ``max_pieces``; its tree
search is seeded, so the same mesh and settings give the same pieces.
"""

from __future__ import annotations

import numpy as np
import trimesh


def convex_pieces(mesh: trimesh.Trimesh, max_pieces: int, threshold: float, seed: int) -> list[np.ndarray]:
    """Vertices (K_i, 3) (m, mesh frame) of each convex piece covering the solid ``mesh`` (m)."""
    if mesh.is_convex:
        return [np.asarray(mesh.convex_hull.vertices, np.float64)]
    import coacd

    coacd.set_log_level("error")
    parts = coacd.run_coacd(coacd.Mesh(np.asarray(mesh.vertices) * 1000.0, np.asarray(mesh.faces)),
                            threshold=threshold, max_convex_hull=max_pieces, seed=seed)
    return [np.asarray(trimesh.convex.convex_hull(np.asarray(v) / 1000.0).vertices, np.float64) for v, _ in parts]


def union_volume(pieces: list[np.ndarray]) -> float:
    """Volume (m^3) of the union of the convex hulls of ``pieces`` (overlaps counted once)."""
    hulls = [trimesh.convex.convex_hull(p) for p in pieces]
    if len(hulls) == 1:
        return float(hulls[0].volume)
    return float(trimesh.boolean.union(hulls, engine="manifold").volume)
