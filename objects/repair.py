"""Repairing any triangle mesh with an inside into a closed, outward, manifold solid (m).

Local repairs first, each listed when it changed something: non-finite vertices dropped, duplicate vertices merged,
degenerate and duplicate triangles dropped, winding made consistent and outward (inside-out bodies turned), holes
closed by a fan of triangles around each boundary loop's centroid (a boundary that crosses itself is split into
simple loops first), overlapping bodies united with manifold3d. The result must be a manifold that manifold3d
accepts, and every sampled triangle must face from inside to outside by the generalized winding number
(Jacobson et al. 2013): ``w(c - e n) > 1/2 > w(c + e n)`` at its centroid ``c`` and normal ``n``.

Where that fails (non-manifold edges, self-intersections, a surface with no consistent orientation), the solid is
remeshed: a signed distance on a grid of ``remesh_cells`` cells across the bounding-box diagonal -- the distance to
the surface, its sign from the winding number ``w > 1/2`` -- and its zero level set extracted as a manifold
(manifold3d's marching tetrahedra). That surface is watertight by construction; features smaller than a cell are
rounded off. A remeshed part keeps its original surface (``Repaired.surface``) for rendering.

Refused, in one line: no finite vertex, no triangle of non-zero area (a line), no volume (flat), and a hole
patch larger than ``max_hole_fraction`` of the surface (an open tray, not a solid with a hole).
"""

from __future__ import annotations

from dataclasses import dataclass

import manifold3d
import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from posegrasp.errors import UserError


#: Largest share of the surface area that may face the wrong way after a local repair (slivers whose normal
#: rounding turns); more means the surface crosses itself or holds an inner sheet, and it is remeshed.
INSIDE_OUT_TOLERANCE = 1e-3


@dataclass(frozen=True)
class Repaired:
    """A repaired solid (m), what was done to it, and its volume over the input's.

    ``volume_change``: ``V_solid / V_input - 1``, where ``V_input`` is the signed volume of the cleaned, outward
    input surface with its holes closed where they could be (overlapping bodies count twice).
    ``surface``: the cleaned input surface when the solid was remeshed and that surface covers it (every sampled
    point of the solid within one grid cell of it: no hole a renderer would show through), for rendering; else None.
    """

    mesh: trimesh.Trimesh
    repairs: tuple[str, ...]
    volume_change: float
    remeshed: bool = False
    surface: trimesh.Trimesh | None = None


def _plural(n: int, word: str, words: str | None = None) -> str:
    return f"{n} {word if n == 1 else (words or word + 's')}"


def clean(mesh: trimesh.Trimesh, name: str) -> tuple[trimesh.Trimesh, list[str]]:
    """``mesh`` without non-finite vertices, duplicate vertices, degenerate or duplicate triangles; the repairs made.

    Refuses a mesh with no finite vertex or no triangle of non-zero area."""
    repairs = []
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    finite = np.isfinite(v).all(axis=1)
    if not finite.any():
        raise UserError(f"{name}: every vertex coordinate is NaN or infinite; nothing to import")
    if not finite.all():
        keep = finite[f].all(axis=1)
        repairs.append(f"dropped {_plural(int((~finite).sum()), 'vertex', 'vertices')} with NaN or infinite "
                       f"coordinates and {_plural(int((~keep).sum()), 'triangle')} using them")
        f = f[keep]
    mesh = trimesh.Trimesh(v, f, process=False)
    mesh.remove_unreferenced_vertices()
    n_v, n_f = len(mesh.vertices), len(mesh.faces)
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise UserError(f"{name}: degenerate: every triangle has zero area (a line or a point); a solid part is "
                        "needed")
    if len(mesh.vertices) < n_v:
        repairs.append(f"merged {n_v - len(mesh.vertices)} duplicate vertices")
    if len(mesh.faces) < n_f:
        repairs.append(f"dropped {n_f - len(mesh.faces)} degenerate or duplicate triangles")
    return mesh, repairs


def _edge_counts(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Directed edges (3M, 2) of ``faces`` and how many triangles share each one's undirected edge."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    _, inverse, counts = np.unique(np.sort(edges, axis=1), axis=0, return_inverse=True, return_counts=True)
    return edges, counts[inverse.ravel()]


def boundary_loops(faces: np.ndarray) -> list[np.ndarray] | None:
    """The boundary of an edge-manifold surface as simple vertex loops, each in the direction its triangles
    traverse it; a boundary that crosses itself at a vertex is split there. None when the surface has
    non-manifold edges or its boundary does not chain into loops (inconsistent winding)."""
    edges, counts = _edge_counts(faces)
    if counts.max() > 2:
        return None
    out: dict[int, list[int]] = {}
    for a, b in edges[counts == 1].tolist():
        out.setdefault(a, []).append(b)
    loops = []
    while out:
        path, where = [min(out)], {}
        while True:
            v = path[-1]
            if v not in out:
                return None  # a boundary edge ends where no boundary edge starts
            where[v] = len(path) - 1
            nxt = out[v].pop()
            if not out[v]:
                del out[v]
            if nxt in where:  # closed a simple loop: cut it out, keep walking from there
                i = where[nxt]
                loops.append(np.array(path[i:]))
                for u in path[i + 1:]:
                    where.pop(u)
                del path[i + 1:]
                if nxt not in out:
                    if i != 0 or len(path) != 1:
                        return None
                    break
                continue
            path.append(nxt)
    return loops


def _fan(vertices: np.ndarray, loop: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Triangles (b, a, c) closing the loop around its centroid ``c`` (index ``len(vertices)``), and their area."""
    c = vertices[loop].mean(axis=0)
    a, b = loop, np.roll(loop, -1)
    tris = np.stack([b, a, np.full_like(a, len(vertices))], axis=1)
    pts = np.vstack([vertices, c[None]])[tris]
    area = 0.5 * float(np.linalg.norm(np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0]), axis=1).sum())
    return c, tris, area


def close_holes(mesh: trimesh.Trimesh, name: str, max_fraction: float) -> tuple[trimesh.Trimesh, int] | None:
    """``mesh`` with every boundary loop closed by a fan, and the number closed; None when its boundary is not
    a set of loops. Refuses a hole patch larger than ``max_fraction`` of the surface area."""
    loops = boundary_loops(np.asarray(mesh.faces))
    if loops is None:
        return None
    if not loops:
        return mesh, 0
    v, f, area = np.asarray(mesh.vertices), [np.asarray(mesh.faces)], float(mesh.area)
    for loop in loops:
        c, tris, patch = _fan(v, loop)
        if patch > max_fraction * area:
            raise UserError(f"{name}: has a hole of {patch * 1e6:.4g} mm^2 ({100 * patch / area:.0f} % of its "
                            f"surface) around ({', '.join(f'{x:.4g}' for x in c)}) m, too large to close (an open "
                            "shell, not a solid); close it in a CAD tool or raise max_hole_fraction in --config")
        v = np.vstack([v, c[None]])
        f.append(tris)
    return trimesh.Trimesh(v, np.vstack(f), process=False), len(loops)


def winding_numbers(mesh: trimesh.Trimesh, points: np.ndarray, chunk: int = 2_000_000) -> np.ndarray:
    """Generalized winding number of ``mesh`` at ``points`` (P, 3): 1 inside a closed outward surface, 0 outside,
    graceful across holes. ``w(p) = sum_t Omega_t(p) / 4 pi`` with each triangle's solid angle (Van Oosterom and
    Strackee 1983) ``tan(Omega / 2) = a . (b x c) / (|a||b||c| + (a . b)|c| + (b . c)|a| + (c . a)|b|)``."""
    tri = np.asarray(mesh.triangles, np.float64)
    out = np.zeros(len(points))
    step = max(1, chunk // max(1, len(tri)))
    for i in range(0, len(points), step):
        d = tri[None] - points[i:i + step, None, None, :]  # (p, t, 3, 3)
        a, b, c = d[:, :, 0], d[:, :, 1], d[:, :, 2]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        num = np.einsum("ptk,ptk->pt", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ptk,ptk->pt", a, b) * lc + np.einsum("ptk,ptk->pt", b, c) * la
               + np.einsum("ptk,ptk->pt", c, a) * lb)
        out[i:i + step] = np.arctan2(num, den).sum(axis=1) / (2 * np.pi)
    return out


def faces_inside_out(mesh: trimesh.Trimesh, samples: int = 256, seed: int = 0) -> float:
    """Share of the area of up to ``samples`` triangles (fewer on large meshes: the cost is samples x triangles),
    drawn with probability proportional to their area (a seeded choice), on triangles not facing from inside
    (w > 1/2) to outside: a self-intersection, an overlap or an inner shell shows as triangles with the solid on
    both sides or neither. Triangles of (near) zero area -- a hole patch over collinear boundary vertices -- have no
    defined normal and are never drawn."""
    area = np.asarray(mesh.area_faces, np.float64)
    p = np.where(area > 1e-9 * area.sum(), area, 0.0)
    rng = np.random.default_rng(seed)
    n = min(int(np.clip(4_000_000 // len(mesh.faces), 16, samples)), int(np.count_nonzero(p)))
    idx = rng.choice(len(mesh.faces), n, replace=False, p=p / p.sum())
    eps = 1e-4 * float(np.linalg.norm(mesh.extents))
    c, normal = mesh.triangles_center[idx], mesh.face_normals[idx]
    w = winding_numbers(mesh, np.concatenate([c - eps * normal, c + eps * normal]))
    bad = (w[:n] < 0.5) | (w[n:] > 0.5)
    return float(area[idx][bad].sum() / area[idx].sum())


def _manifold(mesh: trimesh.Trimesh) -> manifold3d.Manifold | None:
    m = manifold3d.Manifold(manifold3d.Mesh(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32)))
    return m if m.status() == manifold3d.Error.NoError and not m.is_empty() else None


def _trimesh(m: manifold3d.Manifold) -> trimesh.Trimesh:
    out = m.to_mesh()
    return trimesh.Trimesh(np.asarray(out.vert_properties[:, :3], np.float64), np.asarray(out.tri_verts, np.int64),
                           process=False)


def unite(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, int, int] | None:
    """The union of ``mesh``'s closed bodies (manifold3d), with the number of bodies before and after (equal when
    none overlap or touch, and then ``mesh`` itself); None when a body is not a manifold."""
    bodies = mesh.split(only_watertight=False)
    parts = [_manifold(b) for b in bodies]
    if any(p is None for p in parts):
        return None
    if len(parts) == 1:
        return mesh, 1, 1
    union = manifold3d.Manifold.batch_boolean(parts, manifold3d.OpType.Add)
    after = len(union.decompose())
    if after == len(parts) and sum(p.volume() for p in parts) - union.volume() <= 1e-9 * union.volume():
        return mesh, len(parts), len(parts)  # apart: neither overlapping nor touching
    return _trimesh(union), len(parts), after


def remesh(mesh: trimesh.Trimesh, cells: int = 64) -> trimesh.Trimesh:
    """A watertight manifold around the inside of ``mesh`` (m): the zero level set of a signed distance on a grid
    of ``cells`` cells across the bounding-box diagonal, its sign from the winding number. Bodies under a
    thousandth of the volume (grid noise) are dropped."""
    h = float(np.linalg.norm(mesh.extents)) / cells
    lo, hi = mesh.bounds[0] - 2 * h, mesh.bounds[1] + 2 * h
    shape = np.ceil((hi - lo) / h).astype(int) + 1
    axes = [lo[i] + h * np.arange(shape[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    n = int(min(2_000_000, max(20_000, 16 * mesh.area / h ** 2)))
    pts = trimesh.sample.sample_surface(mesh, n, seed=0)[0]
    dist, _ = cKDTree(pts).query(grid, workers=1)
    dist = dist.reshape(shape)
    # the sign: winding numbers in the band around the surface; far regions take one winding number each
    near = dist < 1.5 * h
    inside = np.zeros(shape, bool)
    inside[near] = winding_numbers(mesh, grid.reshape(*shape, 3)[near]) > 0.5
    labels, k = ndimage.label(~near)
    if k:
        flat = labels.ravel()
        order = np.argsort(flat, kind="stable")
        first = order[np.searchsorted(flat[order], np.arange(1, k + 1))]
        seeds = grid[first]
        region_in = np.concatenate([[False], winding_numbers(mesh, seeds) > 0.5])
        inside |= region_in[labels]
    sdf = np.where(inside, dist, -dist)

    def f(x: float, y: float, z: float) -> float:  # trilinear interpolation, positive inside
        u = np.clip(((x, y, z) - lo) / h, 0, shape - 1.000001)
        i = u.astype(int)
        t = u - i
        c = sdf[i[0]:i[0] + 2, i[1]:i[1] + 2, i[2]:i[2] + 2]
        c = c[0] * (1 - t[0]) + c[1] * t[0]
        c = c[0] * (1 - t[1]) + c[1] * t[1]
        return float(c[0] * (1 - t[2]) + c[1] * t[2])

    solid = manifold3d.Manifold.level_set(f, [*lo, *hi], h)
    parts = [p for p in solid.decompose() if p.volume() > 1e-3 * solid.volume()]
    if not parts:
        return trimesh.Trimesh()
    return _trimesh(manifold3d.Manifold.batch_boolean(parts, manifold3d.OpType.Add) if len(parts) > 1 else parts[0])


def _flat(mesh: trimesh.Trimesh) -> bool:
    return len(mesh.faces) == 0 or min(mesh.extents) <= 1e-9 or abs(mesh.volume) <= 1e-6 * float(
        np.prod(mesh.extents))


def repair(mesh: trimesh.Trimesh, name: str, max_hole_fraction: float, remesh_cells: int = 64) -> Repaired:
    """A closed, outward, manifold solid from ``mesh`` (m), cleaned by ``clean``, and the repairs made."""
    mesh, repairs = clean(mesh, name)
    if min(mesh.extents) <= 1e-9 * max(float(np.linalg.norm(mesh.extents)), 1e-12):
        raise UserError(f"{name}: degenerate: the mesh is flat (all its vertices on one plane); a solid part is "
                        "needed")
    was_consistent = mesh.is_winding_consistent
    body_flips = _outward(mesh)
    closed = close_holes(mesh, name, max_hole_fraction)
    v_in = abs(float((closed[0] if closed is not None else mesh).volume))
    local = _local(mesh, closed)
    if local is not None:
        solid, steps = local
        if not was_consistent:
            steps.insert(0, "made triangle winding consistent")
        if body_flips:
            steps.insert(0 if was_consistent else 1, f"turned {_plural(body_flips, 'inside-out body')} outward")
        repairs += steps
        surface, remeshed = None, False
    else:
        solid = remesh(mesh, remesh_cells)
        remeshed = True
        surface = mesh if _covers(mesh, solid, float(np.linalg.norm(mesh.extents)) / remesh_cells) else None
        repairs.append(f"remeshed watertight ({remesh_cells} cells across; the surface had non-manifold edges, "
                       "self-intersections or no consistent orientation)")
    if _flat(solid):
        raise UserError(f"{name}: degenerate: the mesh encloses no volume (flat or a single sheet); a solid part "
                        "is needed")
    change = float(solid.volume) / v_in - 1.0 if v_in > 0 else 0.0
    return Repaired(mesh=solid, repairs=tuple(repairs), volume_change=change, remeshed=remeshed, surface=surface)


def _covers(surface: trimesh.Trimesh, solid: trimesh.Trimesh, h: float, n: int = 4000) -> bool:
    """Whether ``surface`` lies over all of ``solid``: ``n`` seeded samples of the solid within ``h`` (m) of a dense
    sampling of the surface (one point per (h/4)^2 of its area, at most 10^6)."""
    if len(solid.faces) == 0:
        return False
    m = int(min(1_000_000, max(n, 16 * surface.area / h ** 2)))
    ref = trimesh.sample.sample_surface(surface, m, seed=0)[0]
    probe = trimesh.sample.sample_surface(solid, n, seed=1)[0]
    return bool((cKDTree(ref).query(probe, workers=1)[0] <= h).all())


def _outward(mesh: trimesh.Trimesh) -> int:
    """Make the winding consistent and each body outward, in place; the number of bodies turned."""
    with np.errstate(divide="ignore", invalid="ignore"):  # a flat body's centre of mass is 0/0; its volume is 0
        before = [float(b.volume) for b in mesh.split(only_watertight=False)] if mesh.body_count > 1 else [
            float(mesh.volume)]
    mesh.fix_normals()
    return sum(v < 0 for v in before) if mesh.is_winding_consistent else 0


def _local(mesh: trimesh.Trimesh, closed: tuple[trimesh.Trimesh, int] | None) -> tuple[trimesh.Trimesh, list[str]] | None:
    """The local repair of an outward mesh whose holes ``close_holes`` closed: overlapping bodies united; None when
    the result is not a clean manifold solid."""
    if closed is None:
        return None
    mesh, holes = closed
    steps = [f"closed {_plural(holes, 'hole')}"] if holes else []
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)
    if not (mesh.is_watertight and mesh.is_winding_consistent) or mesh.volume <= 0:
        return None
    united = unite(mesh)
    if united is None:
        return None
    mesh, before, after = united
    if after < before:
        steps.append(f"united {before} overlapping or touching bodies into {_plural(after, 'solid')}")
    if faces_inside_out(mesh) > INSIDE_OUT_TOLERANCE:
        return None
    return mesh, steps
