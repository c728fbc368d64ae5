"""The shipped object set of blocks: files, units, symmetries, collision primitives, masses, reproducibility."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull, cKDTree

from posegrasp import ASSETS
from posegrasp.catalog import PartType, load_catalog, sample_surface, symmetry_transforms
from posegrasp.errors import UserError
from posegrasp.geometry import axis_angle_R, make_T, quat_to_R, transform_points

BLOCKS = ASSETS / "blocks"
NAMES = ["cube", "long_cuboid", "brick_2x4", "brick_2x2", "cylinder", "triangular_prism", "arch", "l_block"]


@pytest.fixture(scope="module")
def catalog() -> dict[str, PartType]:
    return load_catalog()


def _mesh(b: PartType) -> trimesh.Trimesh:
    return trimesh.Trimesh(b.vertices, b.faces, process=False)


def test_all_blocks_load_in_id_order(catalog):
    assert list(catalog) == NAMES
    assert [b.obj_id for b in catalog.values()] == list(range(1, 9))
    assert load_catalog() is not catalog and load_catalog()["cube"] is catalog["cube"]  # cached


def test_the_blocks_are_the_default_object_set(catalog):
    from posegrasp.objset import load_object_set

    assert [o.name for o in load_object_set(BLOCKS).objects] == NAMES
    assert load_catalog(BLOCKS)["cube"] is catalog["cube"] and load_catalog(str(BLOCKS))["arch"] is catalog["arch"]
    assert all(b.upright_quat == (1.0, 0.0, 0.0, 0.0) for b in catalog.values())  # +z up as they rest
    assert not (BLOCKS / "catalog.json").exists()


def test_meshes_watertight_and_graspable(catalog):
    for b in catalog.values():
        m = _mesh(b)
        assert m.is_watertight and m.is_winding_consistent and m.volume > 0, b.name
        ext = b.vertices.max(0) - b.vertices.min(0)
        np.testing.assert_allclose(ext, b.extents, atol=1e-6)
        np.testing.assert_allclose((b.vertices.max(0) + b.vertices.min(0)) / 2, 0.0, atol=1e-6)  # bbox centre
        assert np.all((ext >= 0.02) & (ext <= 0.08)) and min(ext[:2]) <= 0.045, b.name
        assert ext[0] >= ext[1] - 1e-9, b.name  # x along the longest horizontal side


def test_ply_in_millimetres_matching_catalog(catalog):
    for b in catalog.values():
        m = trimesh.load(BLOCKS / "models" / f"obj_{b.obj_id:06d}.ply", process=False, force="mesh")
        assert np.all((m.extents >= 20) & (m.extents <= 80)), b.name
        np.testing.assert_allclose(m.extents / 1000.0, b.extents, atol=1e-6)
        assert len(m.vertex_normals) == len(m.vertices)


def _max_nn(points: np.ndarray, reference: cKDTree) -> float:
    return float(reference.query(points)[0].max())


def test_symmetries_map_surface_onto_itself(catalog):
    for b in catalog.values():
        ref = cKDTree(np.vstack([b.vertices, sample_surface(b, 100_000, seed=1)]))
        pts = sample_surface(b, 1000, seed=0)
        Ts = symmetry_transforms(b, n_continuous=12)
        np.testing.assert_allclose(Ts[0], np.eye(4))
        assert len(Ts) == (1 + len(b.symmetries_discrete)) * (12 if b.symmetries_continuous else 1)
        for T in Ts:
            np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
            assert _max_nn(transform_points(T, pts), ref) < 1e-3, b.name


def test_symmetry_counts(catalog):
    counts = {n: (len(b.symmetries_discrete), len(b.symmetries_continuous)) for n, b in catalog.items()}
    assert counts == {"cube": (23, 0), "long_cuboid": (7, 0), "brick_2x4": (1, 0), "brick_2x2": (3, 0),
                      "cylinder": (1, 1), "triangular_prism": (5, 0), "arch": (1, 0), "l_block": (1, 0)}


def test_non_symmetries_rejected(catalog):
    cases = [("brick_2x4", [1, 0, 0], np.pi / 2), ("brick_2x4", [0, 0, 1], np.pi / 2),
             ("brick_2x2", [1, 0, 0], np.pi), ("arch", [1, 0, 0], np.pi), ("l_block", [0, 0, 1], np.pi)]
    for name, axis, angle in cases:
        b = catalog[name]
        ref = cKDTree(np.vstack([b.vertices, sample_surface(b, 100_000, seed=1)]))
        T = make_T(axis_angle_R(np.array(axis, float), angle), np.zeros(3))
        assert _max_nn(transform_points(T, sample_surface(b, 1000, seed=0)), ref) > 3e-3, (name, axis)


def _primitive_volume(p: dict) -> float:
    if p["type"] == "box":
        return 8.0 * float(np.prod(p["size"]))
    if p["type"] == "cylinder":
        return float(np.pi * p["size"][0] ** 2 * 2.0 * p["size"][1])
    assert p["type"] == "mesh"
    return float(trimesh.convex.convex_hull(np.asarray(p["vertices"])).volume)


def test_collision_primitives_match_volume(catalog):
    for b in catalog.values():
        vol = _mesh(b).volume
        prims = b.collision
        assert abs(sum(_primitive_volume(p) for p in prims) / vol - 1.0) < 0.15, b.name
        for p in prims:
            if p["type"] == "mesh":  # a convex piece: its hull adds nothing
                v = np.asarray(p["vertices"])
                assert ConvexHull(v).vertices.size == len(v)
            else:
                assert len(p["size"]) == {"box": 3, "cylinder": 2}[p["type"]] and len(p["quat"]) == 4
    assert len(catalog["arch"].collision) >= 3 and len(catalog["l_block"].collision) == 2
    assert sum(p["type"] == "cylinder" for p in catalog["brick_2x4"].collision) == 8


def _primitive_mesh(p: dict) -> trimesh.Trimesh:
    if p["type"] == "mesh":
        return trimesh.convex.convex_hull(np.asarray(p["vertices"]))
    T = make_T(quat_to_R(np.asarray(p["quat"])), np.asarray(p["pos"]))
    if p["type"] == "box":
        return trimesh.creation.box(extents=2.0 * np.asarray(p["size"]), transform=T)
    return trimesh.creation.cylinder(radius=p["size"][0], height=2.0 * p["size"][1], sections=64, transform=T)


def test_collision_primitives_lie_inside_the_solid(catalog):
    for b in catalog.values():
        solid = _mesh(b)
        for p in b.collision:
            piece = _primitive_mesh(p)
            inside = trimesh.boolean.intersection([solid, piece], engine="manifold").volume
            assert inside > 0.98 * piece.volume, (b.name, p)


def test_masses_plausible(catalog):
    for b in catalog.values():
        assert 0.005 <= b.mass <= 0.2, b.name
        assert b.mass == pytest.approx(1050.0 * _mesh(b).volume, rel=1e-3)


def test_a_folder_that_is_no_object_set_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="is not an object set"):
        load_catalog(tmp_path)


def test_generator_is_reproducible(tmp_path):
    script = BLOCKS / "make_blocks.py"
    subprocess.run([sys.executable, str(script), "--out", str(tmp_path)], check=True, capture_output=True)
    shipped = sorted(p.relative_to(BLOCKS) for p in BLOCKS.rglob("*") if p.is_file() and p.suffix in (".ply", ".json"))
    fresh = sorted(p.relative_to(tmp_path) for p in Path(tmp_path).rglob("*") if p.is_file())
    assert fresh == shipped
    for rel in shipped:
        assert (tmp_path / rel).read_bytes() == (BLOCKS / rel).read_bytes(), rel
