"""Symmetries of a solid mesh, found numerically and checked against its surface (BOP style).

A transform ``T`` is a symmetry when it maps the surface onto itself within a tolerance ``tol``: every checked
point (mesh vertices and seeded surface samples) moved by ``T`` and by ``T^-1`` lies within ``tol`` of the surface
(exact point-to-triangle distance; a nearest-sample distance, an upper bound, clears most points first).

Candidates come from the inertia tensor ``I`` about the centre of mass ``c``: a symmetry ``R`` (about ``c``)
keeps the mass distribution, so ``R I R^T = I`` and ``R`` permutes the principal axes up to sign:

- three distinct principal moments: only the half turns about the three principal axes;
- one distinct axis ``a`` (two equal moments): turns about ``a`` (continuous when turns by 0.3 and 1.9 rad are
  symmetries, else the largest ``n <= max_fold`` whose ``2 pi / n`` turn is), and half turns about axes
  perpendicular to ``a``; such a flip takes a vertex farthest from ``a`` to another one at the opposite height, so
  its axis bisects the two vertices' angles about ``a``, which gives the candidates;
- three equal moments (cube, regular polyhedra, sphere): turns by ``2 pi / n`` (n = 2..6) and continuous turns
  about the directions from ``c`` to the convex hull's vertices, edge midpoints and face normals.

Output follows BOP: discrete symmetries (4x4, m, identity excluded) and continuous ones ``(axis, offset)``, the
rotation about the line through ``offset`` along ``axis``; with a continuous symmetry the discrete list keeps one
transform per coset of it (a cylinder: its continuous axis and one flip).
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from posegrasp.geometry import axis_angle_R, make_T

_EIG_TOL = 0.05  # principal moments within this fraction of the largest count as equal
_CONT_ANGLES = (0.3, 1.9)  # rad: turns that only a continuous symmetry (or a very high fold) passes
_POLY_FOLDS = (6, 5, 4, 3, 2)  # the folds of the polyhedral groups' axes, highest first
_MAX_HULL_AXES = 26  # per kind of hull feature, in the isotropic case


class Surface:
    """Point-to-surface distance tests on a mesh (m)."""

    def __init__(self, mesh: trimesh.Trimesh, n_dense: int, seed: int):
        self.mesh = mesh
        self.lo, self.hi = mesh.bounds
        dense, _ = trimesh.sample.sample_surface(mesh, n_dense, seed=seed + 1)
        self.tree = cKDTree(np.vstack([mesh.vertices, dense]))

    def within(self, q: np.ndarray, tol: float) -> bool:
        """True when every point of ``q`` (N, 3) lies within ``tol`` of the surface."""
        if np.any(q.min(0) < self.lo - tol) or np.any(q.max(0) > self.hi + tol):
            return False
        far = q[self.tree.query(q)[0] > tol]  # the rest is within tol of a sample, so of the surface
        for s in range(0, len(far), 128):  # exact, a chunk at a time, stopping at the first miss
            if trimesh.proximity.closest_point(self.mesh, far[s:s + 128])[1].max() > tol:
                return False
        return True


class _Checker:
    """Whether a rotation about ``c`` maps the surface onto itself (checked both ways, within ``tol``)."""

    def __init__(self, mesh: trimesh.Trimesh, c: np.ndarray, tol: float, n_points: int, seed: int):
        rng = np.random.default_rng(seed)
        v = np.asarray(mesh.vertices)
        verts = v[np.sort(rng.choice(len(v), size=min(len(v), n_points // 3), replace=False))]
        samples, _ = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
        self.pts = np.vstack([samples, verts])
        self.surface = Surface(mesh, 20 * n_points, seed)
        self.c, self.tol = c, tol

    def __call__(self, R: np.ndarray) -> bool:
        q = self.pts - self.c
        return all(self.surface.within(q[:128] @ M.T + self.c, self.tol) for M in (R, R.T)) and \
            all(self.surface.within(q @ M.T + self.c, self.tol) for M in (R, R.T))

    def continuous(self, axis: np.ndarray) -> bool:
        return all(self(axis_angle_R(axis, a)) for a in _CONT_ANGLES)


def _unit(v: np.ndarray) -> np.ndarray:
    """``v`` normalised, its sign fixed so the largest component is positive, float noise rounded away."""
    v = v / np.linalg.norm(v)
    v = v * np.sign(v[np.argmax(np.abs(v))])
    return np.round(v, 12) + 0.0


def _distinct_axes(dirs: np.ndarray, limit: int) -> list[np.ndarray]:
    """Up to ``limit`` directions of ``dirs`` (N, 3), distinct up to sign, in input order."""
    out: list[np.ndarray] = []
    for d in dirs:
        if np.linalg.norm(d) < 1e-12:
            continue
        u = _unit(d)
        if all(abs(abs(u @ w) - 1.0) > 1e-6 for w in out):
            out.append(u)
        if len(out) == limit:
            break
    return out


def _flip_candidates(mesh: trimesh.Trimesh, c: np.ndarray, a: np.ndarray, tol: float) -> list[np.ndarray]:
    """Axes perpendicular to ``a`` through ``c`` that a half turn of the mesh could be about."""
    hull = np.asarray(mesh.convex_hull.vertices) - c
    h = hull @ a
    radial = hull - h[:, None] * a
    r = np.linalg.norm(radial, axis=1)
    far = np.flatnonzero(r > r.max() - tol)
    i = far[0]
    mates = far[np.abs(h[far] + h[i]) <= tol]  # a flip sends height h to -h
    dirs = [radial[i] / r[i] + radial[j] / r[j] for j in mates]  # bisectors of the two angles about a
    dirs = [d if np.linalg.norm(d) > 1e-6 else np.cross(a, radial[i]) for d in dirs]
    return _distinct_axes(np.array(dirs), len(dirs))


def _turns(axis: np.ndarray, n: int) -> list[np.ndarray]:
    return [axis_angle_R(axis, 2 * np.pi * k / n) for k in range(1, n)]


def _hull_axes(mesh: trimesh.Trimesh, c: np.ndarray) -> list[np.ndarray]:
    """Directions from ``c`` to the hull's vertices and edge midpoints, and its (merged) face normals."""
    hull = mesh.convex_hull
    v = np.asarray(hull.vertices)
    far_first = np.argsort(-np.linalg.norm(v - c, axis=1), kind="stable")
    normals = np.asarray(hull.facets_normal) if len(hull.facets) else np.asarray(hull.face_normals)
    mids = np.asarray(hull.vertices)[hull.edges_unique].mean(axis=1) - c
    return (_distinct_axes(v[far_first] - c, _MAX_HULL_AXES) + _distinct_axes(mids, _MAX_HULL_AXES)
            + _distinct_axes(normals, _MAX_HULL_AXES))


def _rotation_key(R: np.ndarray) -> tuple:
    """Order rotations by angle, then axis."""
    angle = float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    w, V = np.linalg.eig(R)
    axis = _unit(np.real(V[:, np.argmin(np.abs(w - 1))]))
    return (round(angle, 6), *(-np.round(axis, 6)))


def _dedupe(rotations: list[np.ndarray]) -> list[np.ndarray]:
    out: list[np.ndarray] = []
    for R in rotations:
        if np.abs(R - np.eye(3)).max() > 1e-6 and all(np.abs(R - Q).max() > 1e-6 for Q in out):
            out.append(R)
    return sorted(out, key=_rotation_key)


def _one_per_coset(discrete: list[np.ndarray], axes: list[np.ndarray]) -> list[np.ndarray]:
    """With continuous symmetries about ``axes``, one rotation per image of the axes (identity's dropped)."""
    def image(R: np.ndarray) -> tuple:
        return tuple(np.round(R @ a, 6).tobytes() for a in axes)

    seen, kept = {image(np.eye(3))}, []
    for R in discrete:
        if image(R) not in seen:
            seen.add(image(R))
            kept.append(R)
    return kept


def find_symmetries(mesh: trimesh.Trimesh, center_of_mass: np.ndarray, inertia: np.ndarray, tol: float,
                    n_points: int = 1500, max_fold: int = 24, seed: int = 0
                    ) -> tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
    """Discrete (4x4, m, identity excluded) and continuous ``(axis, offset m)`` symmetries of ``mesh`` (m).

    ``inertia`` (3, 3) is about ``center_of_mass``; ``tol`` (m) is the largest surface deviation a symmetry may
    cause; ``n_points`` surface samples (plus up to ``n_points / 3`` vertices) are checked per candidate.
    """
    c = np.asarray(center_of_mass, np.float64)
    check = _Checker(mesh, c, tol, n_points, seed)
    lam, E = np.linalg.eigh(inertia)
    same = np.abs(np.diff(lam)) <= _EIG_TOL * lam.max()
    axes = [_unit(E[:, i]) for i in range(3)]
    cont: list[np.ndarray] = []
    if not same.any():  # three distinct moments
        found = [axis_angle_R(a, np.pi) for a in axes]
    elif same.all():  # isotropic
        found = []
        for a in _hull_axes(mesh, c):
            if check.continuous(a):
                cont.append(a)
                if len(_distinct_axes(np.array(cont), 3)) == 3:
                    break  # a sphere
                continue
            n = next((n for n in _POLY_FOLDS if check(axis_angle_R(a, 2 * np.pi / n))), 0)
            found += _turns(a, n) if n else []
        cont = _distinct_axes(np.array(cont), 3) if cont else []
        if len(cont) == 3:  # a sphere turns about every axis: its three principal ones say so best
            cont, found = axes, []
    else:  # one distinct axis a
        a = axes[2] if same[0] else axes[0]
        if check.continuous(a):
            cont, found = [a], [axis_angle_R(axes[1], np.pi)]
        else:
            n = next((n for n in range(max_fold, 1, -1) if check(axis_angle_R(a, 2 * np.pi / n))), 0)
            found = (_turns(a, n) if n else []) + [axis_angle_R(u, np.pi) for u in _flip_candidates(mesh, c, a, tol)]
    discrete = [R for R in _dedupe(found) if check(R)]
    if cont:
        discrete = _one_per_coset(discrete, cont)
    return [make_T(R, c - R @ c) for R in discrete], [(a, c.copy()) for a in cont]  # R about c
