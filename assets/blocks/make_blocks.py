"""Generate the shipped object set of the eight building blocks: BOP models plus MuJoCo collision primitives.

Usage::

    .venv/bin/python assets/blocks/make_blocks.py [--out DIR]   # default: assets/blocks

Writes, deterministically (same inputs and library versions give byte-identical files):

- ``models/obj_00000N.ply``: watertight triangle meshes, binary PLY with vertex normals, in
  MILLIMETRES (BOP convention).
- ``models/models_info.json``: BOP ``models_info`` keyed by ``str(obj_id)``: ``diameter`` (mm, largest
  distance between two vertices), ``min_x/y/z`` and ``size_x/y/z`` (mm), ``symmetries_discrete``
  (row-major 4x4, translation in mm, identity excluded) and ``symmetries_continuous``
  (``{"axis": [..], "offset": [.. mm]}``).
- ``objects/obj_00000N.json`` and ``objectset.json``: the folder is an object set (``posegrasp.objset``,
  ``docs/objects.md``), the default one every command uses. Per block, in SI units (m, kg): mass from ABS
  density x mesh volume, a friction hint (MuJoCo's sliding/torsional/rolling triple), a colour, ``upright``
  (the object-frame direction of the face it stands on upright, studs up and arch on its feet, the rotation
  ``quat`` standing it so, the identity, and whether its top and bottom are flat enough to stack: read by the
  kitting and stack tasks) and ``collision``: MuJoCo primitives in the object frame (box half-sizes, cylinder
  ``[radius, half_height]``, or a convex ``mesh`` given by its vertices) whose union approximates the solid
  within 10 % of its volume. Non-convex blocks are split into convex pieces; no piece is a hull over a
  non-convex part.

Object frame: origin at the centre of the axis-aligned bounding box, +z up in the block's natural
resting pose (studs up, arch legs down), x along the longest horizontal side.

Symmetries are found numerically, not written by hand. Candidate rotations are the 24 rotations
of the cube group (signed permutation matrices with determinant +1) composed with rotations by
0/120/240 degrees about x, y and z (so 3-fold axes such as the triangular prism's, along x, are
covered). A symmetry must fix the centre of mass ``c`` (not the bbox centre: the prism's and the
L-block's differ from it), so each candidate rotation ``R`` is applied about ``c``:
``T = [R | c - R c]``. ``T`` is kept when it maps the surface onto itself: every one of the mesh
vertices and 1500 seeded surface samples, mapped by ``T`` and by ``T^-1``, lies within
``SYM_TOL_MM`` (0.5 mm) of the surface. That is a one-sided maximum over point-to-surface distances,
stricter than a symmetric Chamfer distance between samples; it is computed exactly (point-to-triangle)
for the points that the distance to the nearest of 60000 dense samples, an upper bound, does not
already clear. Continuous symmetry about the x, y or z axis through ``c`` is detected
the same way with rotations by 0.3 and 1.9 rad (a 48-gon cylinder deviates by 0.03 mm). Where a
continuous symmetry exists, the discrete list keeps one rotation per coset of it (for the
cylinder: the 180-degree flip about x), as BOP expects.
"""

from __future__ import annotations

import argparse
import itertools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, cKDTree
from scipy.spatial.distance import pdist

from posegrasp.io import write_bytes, write_json
from posegrasp.objset import FORMAT, MANIFEST, VERSION

HERE = Path(__file__).resolve().parent
DENSITY_ABS = 1050.0  # kg/m^3
FRICTION = (0.5, 0.005, 0.0001)  # MuJoCo geom friction: sliding, torsional, rolling
SYM_TOL_MM = 0.5
SYM_SAMPLES = 1500
SEED = 0
CYL_SECTIONS = 48
STUD_SECTIONS = 32
ARCH_SECTIONS = 64

# Duplo-like bricks (mm): 2x4 body 63.6 x 31.8 x 19.2, stud pitch 15.9.
BRICK_PITCH = 15.9
BRICK_H = 19.2
STUD_R = 4.7
STUD_H = 4.5


@dataclass
class Block:
    """A block as built, in millimetres, in a build frame (shifted to the bbox centre at the end)."""

    obj_id: int
    name: str
    mesh: trimesh.Trimesh
    collision: list[dict] = field(default_factory=list)
    rgba: tuple[float, float, float, float] = (0.8, 0.8, 0.8, 1.0)
    flat_top: bool = True  # upright (-z face down), its top is one flat face another block can stand on ...
    flat_bottom: bool = True  # ... and its bottom rests flat on a flat top (the kitting and stack tasks)


# ----------------------------------------------------------------------------- primitives (mm)


def _box_prim(lo: np.ndarray, hi: np.ndarray) -> dict:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return {"type": "box", "size": (hi - lo) / 2, "pos": (hi + lo) / 2, "quat": [1.0, 0.0, 0.0, 0.0]}


def _cyl_prim(r: float, z0: float, z1: float, xy: tuple[float, float] = (0.0, 0.0)) -> dict:
    return {"type": "cylinder", "size": [r, (z1 - z0) / 2], "pos": [xy[0], xy[1], (z0 + z1) / 2],
            "quat": [1.0, 0.0, 0.0, 0.0]}


def _box_mesh(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((hi + lo) / 2))


def _cyl_mesh(r: float, z0: float, z1: float, xy=(0.0, 0.0), sections: int = CYL_SECTIONS) -> trimesh.Trimesh:
    T = trimesh.transformations.translation_matrix([xy[0], xy[1], (z0 + z1) / 2])
    return trimesh.creation.cylinder(radius=r, height=z1 - z0, sections=sections, transform=T)


def _clean(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Merge vertices, snap float noise to 0.1 um, check it is a closed, outward-oriented solid."""
    v = np.round(np.asarray(mesh.vertices, float), 4) + 0.0  # manifold3d works in float32
    out = trimesh.Trimesh(vertices=v, faces=np.asarray(mesh.faces), process=True)
    assert out.is_watertight and out.is_winding_consistent and out.volume > 0, "mesh is not a closed solid"
    return out


# ----------------------------------------------------------------------------- the eight blocks


def cube() -> Block:
    s = 40.0
    return Block(1, "cube", _box_mesh([0, 0, 0], [s, s, s]), [_box_prim([0, 0, 0], [s, s, s])],
                 (0.85, 0.15, 0.15, 1.0))


def long_cuboid() -> Block:
    lo, hi = [0, 0, 0], [80.0, 25.0, 25.0]
    return Block(2, "long_cuboid", _box_mesh(lo, hi), [_box_prim(lo, hi)], (0.15, 0.45, 0.85, 1.0))


def _brick(obj_id: int, name: str, nx: int, ny: int, rgba) -> Block:
    hi = np.array([nx * BRICK_PITCH, ny * BRICK_PITCH, BRICK_H])
    parts, prims = [_box_mesh([0, 0, 0], hi)], [_box_prim([0, 0, 0], hi)]
    for i, j in itertools.product(range(nx), range(ny)):
        xy = ((i + 0.5) * BRICK_PITCH, (j + 0.5) * BRICK_PITCH)
        # Studs start 1 mm inside the body so the union has no coplanar faces.
        parts.append(_cyl_mesh(STUD_R, BRICK_H - 1.0, BRICK_H + STUD_H, xy, STUD_SECTIONS))
        prims.append(_cyl_prim(STUD_R, BRICK_H, BRICK_H + STUD_H, xy))
    return Block(obj_id, name, trimesh.boolean.union(parts, engine="manifold"), prims, rgba, flat_top=False)


def cylinder() -> Block:
    r, h = 15.0, 40.0
    return Block(5, "cylinder", _cyl_mesh(r, 0.0, h), [_cyl_prim(r, 0.0, h)], (0.95, 0.75, 0.1, 1.0))


def triangular_prism() -> Block:
    """Equilateral triangle (side 40 mm) in the y-z plane, extruded 50 mm along x, lying on a face."""
    side, length = 40.0, 50.0
    tri = np.array([[0.0, 0.0], [side, 0.0], [side / 2, side * np.sqrt(3) / 2]])  # (y, z)
    v = np.array([[x, y, z] for x in (0.0, length) for y, z in tri])
    faces = np.array([[0, 2, 1], [3, 4, 5],  # x = 0 and x = length caps
                      [0, 1, 4], [0, 4, 3],  # bottom (z = 0)
                      [1, 2, 5], [1, 5, 4],
                      [2, 0, 3], [2, 3, 5]])
    mesh = trimesh.Trimesh(v, faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    return Block(6, "triangular_prism", mesh, [{"type": "mesh", "vertices": v}], (0.2, 0.7, 0.3, 1.0), flat_top=False)


def arch() -> Block:
    """64 x 30 x 36 mm block minus a half cylinder (r 16 mm, axis y) from below: two 16 mm legs."""
    L, W, H, r = 64.0, 30.0, 36.0, 16.0
    body = _box_mesh([-L / 2, 0, 0], [L / 2, W, H])
    T = trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])
    T[:3, 3] = [0.0, W / 2, 0.0]
    hole = trimesh.creation.cylinder(radius=r, height=W + 10.0, sections=ARCH_SECTIONS, transform=T)
    mesh = trimesh.boolean.difference([body, hole], engine="manifold")
    prims = [_box_prim([-L / 2, 0, r], [L / 2, W, H])]  # top, above the crown of the arch
    for s in (-1.0, 1.0):
        prims.append(_box_prim(*_xbox(s * r, s * L / 2, W, 0.0, r)))  # leg
        # Boxes inscribed between the arc and the leg, in bands of equal angle.
        th = np.deg2rad([22.5, 45.0, 67.5, 90.0])
        for a, b in zip(th[:-1], th[1:]):
            x_in, z0, z1 = r * np.cos(a), r * np.sin(a), r * np.sin(b)
            prims.append(_box_prim(*_xbox(s * x_in, s * r, W, z0, z1)))
    return Block(7, "arch", mesh, prims, (0.6, 0.3, 0.75, 1.0))


def _xbox(xa: float, xb: float, w: float, z0: float, z1: float) -> tuple[list[float], list[float]]:
    """Corners of the box between x = xa and x = xb, y in [0, w], z in [z0, z1]."""
    return [min(xa, xb), 0.0, z0], [max(xa, xb), w, z1]


def l_block() -> Block:
    """An upright L in the x-z plane: a 50 mm foot along x and a 50 mm leg up z, 25 x 25 mm section."""
    a, w = 50.0, 25.0
    foot, leg = ([0, 0, 0], [a, w, w]), ([0, 0, w], [w, w, a])
    mesh = trimesh.boolean.union([_box_mesh(*foot), _box_mesh([0, 0, w - 1.0], leg[1])], engine="manifold")
    return Block(8, "l_block", mesh, [_box_prim(*foot), _box_prim(*leg)], (0.95, 0.5, 0.1, 1.0), flat_top=False)


def build_blocks() -> list[Block]:
    """All eight blocks, centred on their bounding boxes (mm)."""
    blocks = [cube(), long_cuboid(), _brick(3, "brick_2x4", 4, 2, (0.9, 0.1, 0.1, 1.0)),
              _brick(4, "brick_2x2", 2, 2, (0.1, 0.35, 0.9, 1.0)), cylinder(), triangular_prism(), arch(),
              l_block()]
    for b in blocks:
        mesh = _clean(b.mesh)
        centre = mesh.bounds.mean(axis=0)
        b.mesh = _clean(mesh.apply_translation(-centre))
        for p in b.collision:
            if p["type"] == "mesh":
                p["vertices"] = np.asarray(p["vertices"], float) - centre
            else:
                p["pos"] = np.asarray(p["pos"], float) - centre
    return blocks


# ----------------------------------------------------------------------------- symmetries


def _point_mesh_distance(points: np.ndarray, tris: np.ndarray, chunk: int = 128) -> np.ndarray:
    """Exact distance (same unit) from each point (N, 3) to a triangle soup (M, 3, 3)."""
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    edges = [(a, b), (b, c), (c, a)]
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        p = points[s:s + chunk, None, :]  # (k, 1, 3)
        d_plane = np.einsum("kmi,mi->km", p - a, n)
        q = p - d_plane[..., None] * n
        inside = np.ones(d_plane.shape, bool)
        for u, v in edges:
            inside &= np.einsum("kmi,mi->km", np.cross(v - u, q - u), n) >= -1e-12
        d_edge = np.full(d_plane.shape, np.inf)
        for u, v in edges:
            e = v - u
            t = np.clip(np.einsum("kmi,mi->km", p - u, e) / np.einsum("mi,mi->m", e, e), 0.0, 1.0)
            d_edge = np.minimum(d_edge, np.linalg.norm(p - (u + t[..., None] * e), axis=-1))
        out[s:s + chunk] = np.where(inside, np.abs(d_plane), d_edge).min(axis=1)
    return out


def _rot(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def candidate_rotations() -> list[np.ndarray]:
    """The cube group (24) composed with 0/120/240-degree turns about x, y, z; unique, identity first."""
    cube_group = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[range(3), perm] = signs
            if np.linalg.det(R) > 0:
                cube_group.append(R)
    thirds = [_rot(ax, k * 2 * np.pi / 3) for ax in range(3) for k in (1, 2)]
    unique: dict[bytes, np.ndarray] = {}
    for A in cube_group:
        for B in [np.eye(3)] + thirds:
            R = np.round(A @ B, 12) + 0.0
            unique.setdefault((np.round(R, 6) + 0.0).tobytes(), R)
    return sorted(unique.values(), key=_rotation_key)


def _rotation_key(R: np.ndarray) -> tuple:
    """Order rotations by angle, then by axis (x before y before z, positive first)."""
    angle = float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    if angle < 1e-9:
        return (0.0, 0.0, 0.0, 0.0)
    if np.pi - angle < 1e-6:  # 180 degrees: axis from R + I, sign fixed so the first non-zero is > 0
        M = R + np.eye(3)
        axis = M[:, int(np.argmax(np.linalg.norm(M, axis=0)))]
        axis = axis / np.linalg.norm(axis)
        axis = axis * np.sign(axis[np.flatnonzero(np.abs(axis) > 1e-9)[0]])
    else:
        axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
        axis = axis / np.linalg.norm(axis)
    return (round(angle, 6), *(-np.round(axis, 6)))


def _about(R: np.ndarray, c: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ c
    return T


class _Surface:
    """Point-to-surface distance queries on a mesh (mm), with a fast bound from dense samples."""

    def __init__(self, mesh: trimesh.Trimesh):
        self.tris = np.asarray(mesh.triangles)
        self.lo, self.hi = mesh.bounds
        dense, _ = trimesh.sample.sample_surface(mesh, 40 * SYM_SAMPLES, seed=SEED + 1)
        self.tree = cKDTree(np.vstack([mesh.vertices, dense]))

    def within(self, q: np.ndarray, tol: float) -> bool:
        """True when every point of ``q`` lies within ``tol`` of the surface."""
        if np.any(q.min(0) < self.lo - tol) or np.any(q.max(0) > self.hi + tol):
            return False  # leaves the bounding box
        # The distance to the nearest sample bounds the distance to the surface from above; only the
        # points it does not clear get the exact test, a chunk at a time, stopping at the first miss.
        far = q[self.tree.query(q)[0] > tol]
        return all(_point_mesh_distance(far[s:s + 64], self.tris).max() <= tol for s in range(0, len(far), 64))


def _maps_onto_itself(T: np.ndarray, surface: _Surface, pts: np.ndarray) -> bool:
    """True when ``T`` and ``T^-1`` move every point of ``pts`` to within ``SYM_TOL_MM`` of the surface."""
    return all(surface.within(pts @ M[:3, :3].T + M[:3, 3], SYM_TOL_MM) for M in (T, np.linalg.inv(T)))


def find_symmetries(mesh: trimesh.Trimesh) -> tuple[list[np.ndarray], list[dict]]:
    """Discrete (4x4, mm, identity excluded) and continuous ({axis, offset mm}) symmetries of ``mesh``."""
    c = np.asarray(mesh.center_mass, float)
    samples, _ = trimesh.sample.sample_surface(mesh, SYM_SAMPLES, seed=SEED)
    pts = np.vstack([mesh.vertices, samples])
    surface = _Surface(mesh)
    continuous = []
    for ax in range(3):
        if all(_maps_onto_itself(_about(_rot(ax, ang), c), surface, pts) for ang in (0.3, 1.9)):
            continuous.append({"axis": np.eye(3)[ax], "offset": c})
    discrete = [R for R in candidate_rotations()[1:] if _maps_onto_itself(_about(R, c), surface, pts)]
    if continuous:  # keep one rotation per coset of the continuous group (what it moves the axes to)
        axes = [d["axis"] for d in continuous]
        kept: list[np.ndarray] = []
        for R in discrete:
            image = tuple(np.round(R @ a, 6).tobytes() for a in axes)
            if image == tuple(np.round(a, 6).tobytes() for a in axes):
                continue  # same coset as the identity
            if all(tuple(np.round(Q @ a, 6).tobytes() for a in axes) != image for Q in kept):
                kept.append(R)
        discrete = kept
    return [_about(R, c) for R in discrete], continuous


# ----------------------------------------------------------------------------- output


def _r(x, nd: int):
    """Round floats (nested lists/arrays) to ``nd`` decimals, without negative zeros."""
    a = np.round(np.asarray(x, float), nd) + 0.0
    return a.tolist()


def _prim_volume_mm3(p: dict) -> float:
    if p["type"] == "box":
        return float(8 * np.prod(p["size"]))
    if p["type"] == "cylinder":
        return float(np.pi * p["size"][0] ** 2 * 2 * p["size"][1])
    return float(ConvexHull(np.asarray(p["vertices"])).volume)


def _prim_to_m(p: dict) -> dict:
    if p["type"] == "mesh":
        return {"type": "mesh", "vertices": _r(np.asarray(p["vertices"]) / 1000.0, 9)}
    return {"type": p["type"], "size": _r(np.asarray(p["size"]) / 1000.0, 9),
            "pos": _r(np.asarray(p["pos"]) / 1000.0, 9), "quat": _r(p["quat"], 9)}


def _ply_bytes(mesh: trimesh.Trimesh) -> bytes:
    return trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=True)


def generate(out: Path) -> list[dict]:
    """Build all blocks and write them as an object set under ``out``: models, models_info.json, objects/ and
    objectset.json."""
    models_info, entries, table = {}, [], []
    for b in build_blocks():
        mesh = b.mesh
        ext = mesh.extents
        assert np.all((ext >= 20) & (ext <= 80)) and min(ext[:2]) <= 45, f"{b.name}: not graspable {ext}"
        disc, cont = find_symmetries(mesh)
        hull = mesh.vertices[ConvexHull(mesh.vertices).vertices]
        prim_vol = sum(_prim_volume_mm3(p) for p in b.collision)
        assert abs(prim_vol / mesh.volume - 1) < 0.10, f"{b.name}: collision volume {prim_vol} vs {mesh.volume}"
        write_bytes(out / "models" / f"obj_{b.obj_id:06d}.ply", _ply_bytes(mesh))
        lo = mesh.bounds[0]
        models_info[str(b.obj_id)] = {
            "diameter": round(float(pdist(hull).max()), 6),
            "min_x": round(float(lo[0]), 6) + 0.0, "min_y": round(float(lo[1]), 6) + 0.0,
            "min_z": round(float(lo[2]), 6) + 0.0,
            "size_x": round(float(ext[0]), 6), "size_y": round(float(ext[1]), 6), "size_z": round(float(ext[2]), 6),
            "symmetries_discrete": [_r(T.reshape(-1), 9) for T in disc],
            "symmetries_continuous": [{"axis": _r(d["axis"], 6), "offset": _r(d["offset"], 6)} for d in cont],
        }
        volume_m3 = mesh.volume * 1e-9
        entries.append({
            "obj_id": b.obj_id, "name": b.name, "model": f"models/obj_{b.obj_id:06d}.ply",
            "mass_kg": round(DENSITY_ABS * volume_m3, 6), "density": DENSITY_ABS,
            "volume_m3": round(volume_m3, 12), "friction": list(FRICTION), "rgba": list(b.rgba),
            "collision": [_prim_to_m(p) for p in b.collision],
            "upright": {"down": [0.0, 0.0, -1.0], "flat_top": b.flat_top, "flat_bottom": b.flat_bottom,
                        "quat": [1.0, 0.0, 0.0, 0.0]},
        })
        table.append({"name": b.name, "extents_mm": _r(ext, 2), "mass_g": round(float(DENSITY_ABS * volume_m3 * 1000), 1),
                      "n_discrete": len(disc), "continuous": bool(cont), "faces": len(mesh.faces),
                      "collision_vol_ratio": round(float(prim_vol / mesh.volume), 3)})
    write_json(out / "models" / "models_info.json", models_info)
    for entry in entries:
        write_json(out / "objects" / f"obj_{entry['obj_id']:06d}.json", entry)
    write_json(out / MANIFEST, {
        "format": FORMAT, "version": VERSION,
        "units": "objects/*.json in SI units (m, kg); models/ in BOP's millimetres",
        "frame": "origin at the bounding-box centre, +z up in the resting pose, x along the longest horizontal side",
        "collision_types": "box size = half-sizes; cylinder size = [radius, half_height] along local z; "
                           "mesh = vertices of one convex piece; quat = (w, x, y, z)",
        "objects": [{"obj_id": e["obj_id"], "name": e["name"], "file": f"objects/obj_{e['obj_id']:06d}.json"}
                    for e in entries],
    })
    return table


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=HERE, help="output directory (default: assets/blocks)")
    args = ap.parse_args(argv)
    for row in generate(args.out):
        print(row)


if __name__ == "__main__":
    main()
