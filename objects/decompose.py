"""Collision pieces: a convex decomposition of a solid with CoACD (MuJoCo collides each mesh as its convex hull).

A convex mesh is its own single piece (its hull). Otherwise the solid is first decimated to at most
``collision_faces`` triangles (quadric edge collapse, Garland and Heckbert 1997; fast-simplification) while its
volume stays within ``DECIMATION_VOLUME`` -- a remeshed or scanned surface has ten times more triangles than the
hulls can use, and CoACD's cost grows with them -- then CoACD (Wei et al. 2022) splits it until every piece's
concavity is below ``threshold`` (relative to the bounding box), merging down to at most ``max_pieces``. Its
input is already a closed manifold, so CoACD's own remeshing is off; its tree search is seeded, so the same mesh
and settings give the same pieces.
"""

from __future__ import annotations

import numpy as np
import trimesh

#: Largest relative volume change a decimation may make before a finer one is taken (thin walls collapse first).
DECIMATION_VOLUME = 0.02


def decimated(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    """``mesh`` (m) with at most ``faces`` triangles, or as few more as keep its volume within
    ``DECIMATION_VOLUME`` (each try doubles the count); ``mesh`` itself when it has no more than that."""
    import fast_simplification

    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    while faces < len(f):
        v2, f2 = fast_simplification.simplify(v, f, target_reduction=1.0 - faces / len(f))
        out = trimesh.Trimesh(v2, f2, process=False)
        if abs(out.volume / mesh.volume - 1.0) <= DECIMATION_VOLUME:
            return out
        faces *= 2
    return mesh


def convex_pieces(mesh: trimesh.Trimesh, max_pieces: int, threshold: float, seed: int, faces: int = 3000,
                  iterations: int = 50) -> list[np.ndarray]:
    """Vertices (K_i, 3) (m, mesh frame) of each convex piece covering the solid ``mesh`` (m), found on the solid
    decimated to ``faces`` triangles with ``iterations`` tree-search iterations per cut."""
    if mesh.is_convex:
        return [np.asarray(mesh.convex_hull.vertices, np.float64)]
    import coacd

    coacd.set_log_level("error")
    solid = decimated(mesh, faces)
    parts = coacd.run_coacd(coacd.Mesh(np.asarray(solid.vertices) * 1000.0, np.asarray(solid.faces)),
                            threshold=threshold, max_convex_hull=max_pieces, seed=seed, preprocess_mode="off",
                            mcts_iterations=iterations, mcts_nodes=10, mcts_max_depth=2)
    return [np.asarray(trimesh.convex.convex_hull(np.asarray(v) / 1000.0).vertices, np.float64) for v, _ in parts]


def union_volume(pieces: list[np.ndarray]) -> float:
    """Volume (m^3) of the union of the convex hulls of ``pieces`` (overlaps counted once)."""
    hulls = [trimesh.convex.convex_hull(p) for p in pieces]
    if len(hulls) == 1:
        return float(hulls[0].volume)
    return float(trimesh.boolean.union(hulls, engine="manifold").volume)
