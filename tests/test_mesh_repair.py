"""``objects.repair``: a corpus of defective meshes made in code, each imported as a closed manifold solid with the
expected repairs listed, or refused in one line -- never a traceback."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from helpers import refused

from posegrasp.errors import UserError
from posegrasp.objects.mesh import check_size
from posegrasp.objects.repair import repair

TF = trimesh.transformations
BOX = trimesh.creation.box([0.04, 0.03, 0.02])
CYL = trimesh.creation.cylinder(0.02, 0.06, sections=32)


def _soup(m: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.faces), process=False)


def _drop(m: trimesh.Trimesh, keep: np.ndarray) -> trimesh.Trimesh:
    return trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.faces)[keep], process=False)


def _cat(*ms: trimesh.Trimesh) -> trimesh.Trimesh:
    return _soup(trimesh.util.concatenate(list(ms)))


def _moved(m: trimesh.Trimesh, xyz) -> trimesh.Trimesh:
    m = m.copy()
    m.apply_translation(xyz)
    return m


def crossing_boundary() -> trimesh.Trimesh:
    """Two triangles of the cylinder's side that share only a vertex removed: the boundary crosses itself there
    (as robosuite's can.stl)."""
    f = CYL.faces
    v = np.bincount(f.ravel()).argmax()
    share = np.where((f == v).any(axis=1))[0]
    pairs = [(a, b) for a in share for b in share if a < b and len(set(f[a]) & set(f[b])) == 1]
    keep = np.ones(len(f), bool)
    keep[list(pairs[0])] = False
    return _drop(CYL, keep)


def inside_out() -> trimesh.Trimesh:
    return trimesh.Trimesh(BOX.vertices, BOX.faces[:, ::-1], process=False)


def mixed_winding() -> trimesh.Trimesh:
    f = BOX.faces.copy()
    f[::3] = f[::3, ::-1]
    return trimesh.Trimesh(BOX.vertices, f, process=False)


def self_intersecting() -> trimesh.Trimesh:
    """A box with one corner pushed through the opposite face: one body whose surface crosses itself."""
    v = BOX.vertices.copy()
    i = int(np.argmax(v @ [1, 1, 1]))
    v[i] = [-0.03, 0.0, 0.0]
    return trimesh.Trimesh(v, BOX.faces, process=False)


def nan_coordinates() -> trimesh.Trimesh:
    return _cat(BOX, trimesh.Trimesh([[np.nan, 0, 0], [0, np.nan, 0], [0, 0, 0.01]], [[0, 1, 2]], process=False))


#: name -> (mesh, words each expected repair holds; empty: imported unchanged)
CASES = {
    "clean box": (lambda: BOX, []),
    "triangle soup": (lambda: _soup(trimesh.Trimesh(BOX.triangles.reshape(-1, 3), np.arange(36).reshape(-1, 3),
                                                    process=False)), ["merged"]),
    "duplicate faces": (lambda: trimesh.Trimesh(BOX.vertices, np.vstack([BOX.faces, BOX.faces[:4]]), process=False),
                        ["dropped 4 degenerate or duplicate"]),
    "degenerate faces": (lambda: trimesh.Trimesh(BOX.vertices, np.vstack([BOX.faces, [[0, 0, 1], [2, 2, 2]]]),
                                                 process=False), ["dropped 2 degenerate"]),
    "inside-out": (inside_out, ["turned 1 inside-out body"]),
    "mixed winding": (mixed_winding, ["winding consistent"]),
    "one hole": (lambda: _drop(CYL, CYL.face_normals[:, 2] < 0.5), ["closed 1 hole"]),
    "scattered holes": (lambda: _drop(CYL, np.arange(len(CYL.faces)) % 17 != 0), ["closed 8 holes"]),
    "crossing boundary": (crossing_boundary, ["closed 2 holes"]),
    "open box (T-junction side)": (lambda: _drop(BOX, BOX.face_normals[:, 0] < 0.5), ["closed 1 hole"]),
    "two overlapping bodies": (lambda: _cat(BOX, _moved(BOX, [0.02, 0.01, 0.0])), ["united 2 overlapping or touching bodies"]),
    "two separate bodies": (lambda: _cat(BOX, _moved(BOX, [0.06, 0.0, 0.0])), []),
    "overlapping inside-out body": (lambda: _cat(BOX, _moved(inside_out(), [0.01, 0.0, 0.0])),
                                    ["turned 1 inside-out body", "united"]),
    "body inside another": (lambda: _cat(BOX, trimesh.creation.box([0.01, 0.01, 0.01])), ["united"]),
    "non-manifold edge": (lambda: _cat(BOX, _moved(BOX, [0.04, 0.03, 0.0])), ["remeshed"]),
    "self-intersection": (self_intersecting, ["remeshed"]),
    "NaN coordinates": (nan_coordinates, ["NaN"]),
    "tiny triangles": (lambda: BOX.subdivide().subdivide(), []),
    "100k faces": (lambda: trimesh.creation.icosphere(7, radius=0.03), []),
    "rotated, off the origin": (lambda: _moved(_soup(CYL.copy().apply_transform(TF.rotation_matrix(1.0, [1, 2, 3]))),
                                               [5.0, -3.0, 1.0]), []),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_defective_mesh_is_repaired_into_a_solid(name: str) -> None:
    make, words = CASES[name]
    fixed = repair(make(), name, max_hole_fraction=0.25)
    m = fixed.mesh
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0, name
    for w in words:
        assert any(w in r for r in fixed.repairs), (name, w, fixed.repairs)
    if not words:
        assert not [r for r in fixed.repairs if "merged" not in r], (name, fixed.repairs)
    # the overlap counted once (the input's signed volume counts it twice); a self-crossing surface has no volume
    expected = {"two overlapping bodies": -1 / 6, "overlapping inside-out body": -0.375, "body inside another": -1 / 25}
    if name != "self-intersection":
        assert fixed.volume_change == pytest.approx(expected.get(name, 0.0), abs=0.03), (name, fixed.volume_change)


@pytest.mark.slow
def test_remeshed_solid_keeps_the_volume() -> None:
    """The non-manifold pair of boxes (joined along one edge) keeps its volume within 3 % through the remesh."""
    fixed = repair(CASES["non-manifold edge"][0](), "nm", 0.25)
    assert fixed.remeshed and fixed.surface is not None
    assert fixed.mesh.volume == pytest.approx(2 * BOX.volume, rel=0.03)


REFUSED = {
    "a single triangle": (trimesh.Trimesh([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]], [[0, 1, 2]]), "flat"),
    "a flat square": (trimesh.creation.box([0.05, 0.05, 0.0]), "flat"),
    "a line": (trimesh.Trimesh([[0, 0, 0], [0.01, 0, 0], [0.02, 0, 0]], [[0, 1, 2]], process=False), "degenerate"),
    "NaN only": (trimesh.Trimesh(np.full((3, 3), np.nan), [[0, 1, 2]], process=False), "NaN"),
    "an open tray": (_drop(BOX, BOX.face_normals[:, 2] < 0.5), "too large to close"),
}


@pytest.mark.parametrize("name", list(REFUSED))
def test_mesh_without_volume_is_refused_in_one_line(name: str) -> None:
    mesh, words = REFUSED[name]
    with pytest.raises(UserError) as e:
        check_size(mesh, name, "m", 0.005, 1.0)
        repair(mesh, name, 0.25)
    assert words in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("scale, words", [(1000.0, "pass --unit mm"), (1e-4, "outside the")])
def test_mesh_in_the_wrong_unit_is_refused(capsys, tmp_path: Path, scale: float, words: str) -> None:
    path = tmp_path / "part.stl"
    BOX.copy().apply_scale(scale).export(path)
    refused(capsys, ["objects", "import", path, "--out", tmp_path / "set", "--no-progress"], words)
    assert not (tmp_path / "set").exists()


@pytest.mark.slow
def test_a_remeshed_part_settles_and_is_grasped_by_the_oracle(tmp_path: Path) -> None:
    """A brick with a stray sheet along one edge (a non-manifold edge, as CAD exports leave them) is remeshed, drawn
    with its input surface, and picked and placed by the oracle in both episodes (the scene settles, nothing
    explodes)."""
    import json

    from posegrasp.cli import main

    brick = trimesh.creation.box([0.05, 0.03, 0.025])
    v = brick.vertices
    top_back = [i for i in range(8) if v[i, 1] > 0 and v[i, 2] > 0]  # the edge along x at the top of the +y side
    fin = trimesh.Trimesh(np.vstack([v[top_back], v[top_back].mean(axis=0) + [0.0, 0.004, 0.004]]), [[0, 1, 2]],
                          process=False)
    _cat(brick, fin).export(tmp_path / "brick.stl")
    out = tmp_path / "set"
    assert main(["objects", "import", str(tmp_path / "brick.stl"), "--out", str(out), "--no-progress"]) == 0
    listed = json.loads((out / "objectset.json").read_text())["objects"][0]
    assert any("remeshed" in r for r in listed["repairs"]) and abs(listed["volume_change"]) < 0.05, listed
    assert (out / "objects" / "obj_000001_surface.ply").is_file()
    runs = tmp_path / "runs"
    assert main(["trials", "--objects", str(out), "--episodes", "2", "--blocks", "1", "--seed", "0", "--workers", "1",
                 "--no-progress", "--out", str(runs)]) == 0
    episodes = [json.loads(ln) for ln in (runs / "episodes.jsonl").read_text().splitlines()]
    assert [e["outcome"] for e in episodes] == ["success", "success"], [e.get("failure") for e in episodes]
