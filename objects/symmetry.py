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

The discrete rotations that pass are made a group (closed under composition, a product within the tolerance's
angle of an element counting as that element): unless they are one already, each in turn, those moving the surface
least first, joins with the products it makes with the group so far when every product passes too, else it is left
out (a near-round part's turns about axes a little off, which compose to turns that do not pass). Candidates that
fail by at most twice the tolerance, and are no element of the group, are reported as near symmetries with their
surface error.

Output follows BOP: discrete symmetries (4x4, m, identity excluded) and continuous ones ``(axis, offset)``, the
rotation about the line through ``offset`` along ``axis``; with a continuous symmetry the discrete list keeps one
transform per coset of it (a cylinder: its continuous axis and one flip).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from posegrasp.geometry import axis_angle_R, make_T

_EIG_TOL = 0.05  # principal moments within this fraction of the largest count as equal
_CONT_ANGLES = (0.3, 1.9)  # rad: turns that only a continuous symmetry (or a very high fold) passes
_POLY_FOLDS = (6, 5, 4, 3, 2)  # the folds of the polyhedral groups' axes, highest first
_MAX_HULL_AXES = 26  # per kind of hull feature, in the isotropic case
_NEAR = 2.0  # a failed candidate moving the surface at most this many tolerances is a near symmetry
_CHUNK = 128  # points per exact point-to-surface query


@dataclass(frozen=True)
class Symmetries:
    """What the search found (m, object frame): ``discrete`` 4x4 transforms (identity excluded), ``continuous``
    ``(axis, offset)`` lines; ``near``: rejected rotations about the centre of mass that move the surface at most
    twice the tolerance, ``(T 4x4, largest surface deviation m)``, smallest first; ``left_out``: how many rotations
    within the tolerance were left out because with the others they make no group."""

    discrete: list[np.ndarray]
    continuous: list[tuple[np.ndarray, np.ndarray]]
    near: list[tuple[np.ndarray, float]] = field(default_factory=list)
    left_out: int = 0


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
        for s in range(0, len(far), _CHUNK):  # exact, a chunk at a time, stopping at the first miss
            if trimesh.proximity.closest_point(self.mesh, far[s:s + _CHUNK])[1].max() > tol:
                return False
        return True

    def deviation(self, q: np.ndarray, cap: float) -> float:
        """The largest distance (m) of a point of ``q`` (N, 3) from the surface; infinity once it exceeds ``cap``."""
        if not self.within(q, cap):
            return float("inf")
        bound = self.tree.query(q)[0]  # each at least its exact distance
        order = np.argsort(-bound, kind="stable")
        worst = 0.0
        for s in range(0, len(order), _CHUNK):  # exact, farthest bounds first, until no bound can beat the worst
            idx = order[s:s + _CHUNK]
            if bound[idx[0]] <= worst:
                break
            worst = max(worst, float(trimesh.proximity.closest_point(self.mesh, q[idx])[1].max()))
        return worst


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
        self.failed: list[np.ndarray] = []  # the candidates that did not pass, in the order asked

    def __call__(self, R: np.ndarray) -> bool:
        """Whether candidate ``R`` passes (a failure is kept in ``failed``)."""
        ok = self.passes(R)
        if not ok:
            self.failed.append(R)
        return ok

    def passes(self, R: np.ndarray) -> bool:
        q = self.pts - self.c
        return all(self.surface.within(q[:_CHUNK] @ M.T + self.c, self.tol) for M in (R, R.T)) and \
            all(self.surface.within(q @ M.T + self.c, self.tol) for M in (R, R.T))

    def continuous(self, axis: np.ndarray) -> bool:
        return all(self.passes(axis_angle_R(axis, a)) for a in _CONT_ANGLES)

    def error(self, R: np.ndarray, cap: float) -> float:
        """How far (m) ``R`` moves the checked points off the surface, either way; infinity when over ``cap``."""
        q = self.pts - self.c
        if not all(self.surface.within(q[:_CHUNK] @ M.T + self.c, cap) for M in (R, R.T)):  # most fail here
            return float("inf")
        return max(self.surface.deviation(q @ M.T + self.c, cap) for M in (R, R.T))

    def score(self, R: np.ndarray) -> float:
        """How far (m) ``R`` moves the first ``_CHUNK`` checked points off the surface, either way (what ranks the
        candidates that pass: a quick lower bound of ``error``)."""
        q = self.pts[:_CHUNK] - self.c
        return max(float(trimesh.proximity.closest_point(self.surface.mesh, q @ M.T + self.c)[1].max())
                   for M in (R, R.T))

    def near(self) -> list[tuple[np.ndarray, float]]:
        """The failed candidates that move the surface at most ``_NEAR`` tolerances, with that error (m), smallest
        first."""
        candidates: list[np.ndarray] = []
        for R in _dedupe(self.failed):  # a turn's inverse says nothing more
            if all(np.abs(R.T - Q).max() > 1e-6 for Q in candidates):
                candidates.append(R)
        errors = [(R, self.error(R, _NEAR * self.tol)) for R in candidates]
        return sorted(((R, e) for R, e in errors if e <= _NEAR * self.tol), key=lambda x: x[1])


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


def _index(elements: np.ndarray, R: np.ndarray, same: float) -> int | None:
    """The index of the rotation of ``elements`` (K, 3, 3) within ``same`` rad of rotation ``R``, or None."""
    if not len(elements):
        return None
    cos = (np.einsum("kij,ij->k", elements, R) - 1.0) / 2.0  # cos of the angle of E^T R
    k = int(np.argmax(cos))
    return k if cos[k] >= np.cos(same) else None


def _closure(group: np.ndarray, R: np.ndarray, check: _Checker, same: float, limit: int) -> np.ndarray | None:
    """The group (K, 3, 3) that ``group`` (identity first) and ``R`` generate, or None when one of its new
    elements fails ``check`` or it would grow past ``limit`` elements."""
    out, fresh = group, [R]
    while fresh:
        out = np.concatenate([out, fresh])
        new: list[np.ndarray] = []
        for P in np.concatenate([np.concatenate([A @ out, out @ A]) for A in fresh]):
            if _index(out, P, same) is None and _index(np.asarray(new), P, same) is None:
                if len(out) + len(new) >= limit or not check.passes(P):
                    return None
                new.append(P)
        fresh = new
    return out


def _is_group(elements: np.ndarray, same: float) -> bool:
    """Whether rotations ``elements`` (K, 3, 3, the identity among them) are distinct and closed under
    composition."""
    near = (np.einsum("aij,bij->ab", elements, elements) - 1.0) / 2.0 >= np.cos(same)  # cos of the angle of A^T B
    return int(near.sum()) == len(elements) and all(
        _index(elements, A @ B, same) is not None for A in elements for B in elements)


def _group(rotations: list[np.ndarray], check: _Checker, same: float, limit: int) -> tuple[list[np.ndarray], int]:
    """``rotations`` (in ``_rotation_key`` order) when they and the identity make a group; else the group they
    generate, each joining in turn, those moving the surface least first, when the elements it adds pass ``check``
    (else left out), in ``_rotation_key`` order. Returned without the identity, with how many were left out."""
    if _is_group(np.array([np.eye(3), *rotations]), same):
        return rotations, 0
    group, left_out = np.eye(3)[None], 0
    for R in sorted(rotations, key=check.score):  # the best first
        if _index(group, R, same) is None:
            grown = _closure(group, R, check, same, limit)
            left_out += grown is None
            group = group if grown is None else grown
    return sorted(group[1:], key=_rotation_key), left_out


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
                    n_points: int = 1500, max_fold: int = 24, seed: int = 0) -> Symmetries:
    """Discrete (4x4, m, identity excluded; a group with the identity) and continuous ``(axis, offset m)``
    symmetries of ``mesh`` (m), and the near ones rejected.

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
    same = tol / float(np.linalg.norm(np.asarray(mesh.vertices) - c, axis=1).max())  # rad: one element
    discrete, left_out = _group([R for R in _dedupe(found) if check(R)], check, same, max(60, 2 * max_fold))
    group = np.array([np.eye(3), *discrete])
    near = [(R, e) for R, e in check.near() if _index(group, R, same) is None]
    if cont:
        discrete = _one_per_coset(discrete, cont)
    return Symmetries([make_T(R, c - R @ c) for R in discrete], [(a, c.copy()) for a in cont],  # R about c
                      [(make_T(R, c - R @ c), e) for R, e in near], left_out)


def near_warnings(sym: Symmetries, tol: float, diameter: float, most: int = 3) -> list[str]:
    """One sentence per near symmetry of ``sym`` rejected (the ``most`` nearest; ``tol`` and ``diameter`` in m), and
    one for the turns left out of the group."""
    out = []
    for T, e in sym.near[:most]:
        v = Rotation.from_matrix(T[:3, :3]).as_rotvec()
        axis = _unit(v)
        need = math.ceil(e / diameter * 1e4) / 1e4
        out.append(f"near symmetry rejected: a {np.degrees(np.linalg.norm(v)):.0f} deg turn about "
                   f"({axis[0]:.3f}, {axis[1]:.3f}, {axis[2]:.3f}) through its centre of mass moves its surface "
                   f"{e * 1000:.2f} mm, over the {tol * 1000:.2f} mm tolerance; sym_tol_rel = {need:g} in --config "
                   "admits it")
    if len(sym.near) > most:
        out.append(f"{len(sym.near) - most} more near symmetries rejected")
    if sym.left_out:
        out.append(f"{sym.left_out} turn(s) within the tolerance left out: with the others they make no group")
    return out
