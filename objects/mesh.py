"""Reading a mesh file and repairing it into a closed, outward-oriented solid in metres, centred on its bounding box.

Repairs: duplicate vertices merged, degenerate and duplicate triangles dropped, holes whose boundary is a simple
loop closed by a fan of triangles around the loop's centroid (up to ``max_hole_fraction`` of the surface area),
winding made consistent and outward. A mesh these cannot make a solid is refused with one line naming the file and
the defect (``UserError``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from posegrasp.errors import UserError

#: Metres per unit of ``--unit``.
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}


@dataclass(frozen=True)
class SolidMesh:
    """A repaired mesh (m) centred on its bounding box: ``vertices_obj = vertices_file * scale + offset``."""

    mesh: trimesh.Trimesh
    scale: float  # metres per file unit
    offset: np.ndarray  # (3,) translation applied after scaling (m)
    repairs: tuple[str, ...]  # what was repaired, in words


def check_size(mesh: trimesh.Trimesh, name: str, unit: str, lo: float, hi: float) -> None:
    """Refuse a mesh whose bounding-box diagonal (m) lies outside [lo, hi]: its declared unit is likely wrong."""
    diag = float(np.linalg.norm(mesh.extents))
    if lo <= diag <= hi:
        return
    sizes = {u: diag / UNITS[unit] * s for u, s in UNITS.items()}
    fits = sorted((u for u, d in sizes.items() if lo <= d <= hi), key=lambda u: abs(np.log(sizes[u] / 0.1)))
    hint = f"; is it in {fits[0]}? pass --unit {fits[0]}" if fits else ""
    raise UserError(f"{name}: {diag:.4g} m across with --unit {unit}, outside the {lo:g}-{hi:g} m a tabletop part "
                    f"spans{hint}")


def _boundary_loops(faces: np.ndarray, name: str) -> list[list[tuple[int, int]]]:
    """Directed boundary edges (as the faces traverse them), chained into closed loops."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(edges, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    if counts.max() > 2:
        raise UserError(f"{name}: {int((counts > 2).sum())} edges are shared by more than two triangles "
                        "(non-manifold); fix the model in a CAD tool")
    nxt: dict[int, tuple[int, int]] = {}
    for a, b in edges[counts[inverse.ravel()] == 1]:
        if int(a) in nxt:
            raise UserError(f"{name}: its open boundary crosses itself at a vertex (not a simple hole); fix the "
                            "model in a CAD tool")
        nxt[int(a)] = (int(a), int(b))
    loops = []
    while nxt:
        start = min(nxt)
        loop, v = [], start
        while True:
            if v not in nxt:
                raise UserError(f"{name}: an open boundary does not close into a loop; fix the model in a CAD tool")
            e = nxt.pop(v)
            loop.append(e)
            v = e[1]
            if v == start:
                break
        loops.append(loop)
    return loops


def _close_holes(mesh: trimesh.Trimesh, name: str, max_fraction: float) -> tuple[trimesh.Trimesh, int]:
    """Fan-triangulate every boundary loop around its centroid; refuse a hole larger than ``max_fraction``."""
    loops = _boundary_loops(np.asarray(mesh.faces), name)
    if not loops:
        return mesh, 0
    v, f = [np.asarray(mesh.vertices)], [np.asarray(mesh.faces)]
    area, n = float(mesh.area), len(mesh.vertices)
    for loop in loops:
        ring = np.array([a for a, _ in loop])
        c = np.asarray(mesh.vertices)[ring].mean(axis=0)
        # A boundary edge a->b of an outward face is closed by the triangle b->a->c.
        tris = np.array([[b, a, n] for a, b in loop])
        pts = np.vstack([np.asarray(mesh.vertices), c[None]])[tris]
        patch = 0.5 * np.linalg.norm(np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0]), axis=1).sum()
        if patch > max_fraction * area:
            raise UserError(f"{name}: has a hole of {patch * 1e6:.4g} mm^2 ({100 * patch / area:.0f} % of its "
                            f"surface) around ({', '.join(f'{x:.4g}' for x in c)}) m, too large to close; close it "
                            "in a CAD tool")
        v.append(c[None])
        f.append(tris)
        n += 1
    return trimesh.Trimesh(np.vstack(v), np.vstack(f), process=False), len(loops)


def repair(mesh: trimesh.Trimesh, name: str, max_hole_fraction: float) -> tuple[trimesh.Trimesh, tuple[str, ...]]:
    """A closed, consistently wound, outward solid from ``mesh`` (m), and the list of repairs made."""
    repairs = []
    n_v, n_f = len(mesh.vertices), len(mesh.faces)
    mesh = mesh.copy()
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise UserError(f"{name}: degenerate: every triangle has zero area")
    if len(mesh.vertices) < n_v:
        repairs.append(f"merged {n_v - len(mesh.vertices)} duplicate vertices")
    if len(mesh.faces) < n_f:
        repairs.append(f"dropped {n_f - len(mesh.faces)} degenerate or duplicate triangles")
    was_consistent = mesh.is_winding_consistent
    mesh.fix_normals()  # consistent winding first: the hole fans follow the faces' orientation
    mesh, holes = _close_holes(mesh, name, max_hole_fraction)
    if holes:
        repairs.append(f"closed {holes} hole{'s' if holes > 1 else ''}")
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)
    flipped = mesh.volume < 0
    mesh.fix_normals()
    if not (mesh.is_watertight and mesh.is_winding_consistent):
        raise UserError(f"{name}: not a closed solid after repair (inconsistent triangle orientation, e.g. a "
                        "Moebius-like surface or intersecting shells); fix the model in a CAD tool")
    if not was_consistent or flipped:
        repairs.append("fixed triangle orientation (normals outward)")
    if min(mesh.extents) <= 1e-9 or mesh.volume <= 1e-6 * float(np.prod(mesh.extents)):
        raise UserError(f"{name}: degenerate: the mesh is flat (volume {mesh.volume:.3g} m^3); a solid part is "
                        "needed")
    return mesh, tuple(repairs)


def centred(raw: trimesh.Trimesh, scale: float, label: str, unit: str, max_hole_fraction: float,
            size_range: tuple[float, float]) -> SolidMesh:
    """Size-check and repair ``raw`` (m), then move its bounding-box centre to the origin (``label`` names the mesh
    in error messages)."""
    check_size(raw, label, unit, *size_range)
    mesh, repairs = repair(raw, label, max_hole_fraction)
    offset = -mesh.bounds.mean(axis=0)
    mesh.apply_translation(offset)
    return SolidMesh(mesh=mesh, scale=scale, offset=offset, repairs=repairs)
