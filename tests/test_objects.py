"""``posegrasp objects import|show``: meshes the test makes with trimesh in several forms become an object set whose
collision pieces are convex and cover the mesh, whose symmetries are right, and whose files are byte-identical
when imported twice; bad input is a one-line error with nothing written."""

from __future__ import annotations

import json
import shutil
import textwrap
from pathlib import Path

import numpy as np
import pytest
import trimesh
from helpers import refused
from test_bad_input import snapshot

from posegrasp.catalog import load_catalog
from posegrasp.cli import main
from posegrasp.objects.mass import mass_properties
from posegrasp.objset import load_object_set
from posegrasp.objects.rest import upright
from posegrasp.objects.symmetry import find_symmetries, near_warnings

TF = trimesh.transformations
TILT = TF.rotation_matrix(0.7, [1.0, 2.0, 3.0])


def u_channel() -> trimesh.Trimesh:
    """A 60 x 30 x 40 mm U (a 10 mm base and two 10 mm walls), opening up: not convex."""
    parts = [trimesh.creation.box([0.06, 0.03, 0.01], TF.translation_matrix([0, 0, -0.015]))]
    parts += [trimesh.creation.box([0.01, 0.03, 0.04], TF.translation_matrix([x, 0, 0])) for x in (-0.025, 0.025)]
    return trimesh.boolean.union(parts, engine="manifold")


def open_cylinder() -> trimesh.Trimesh:
    """A 32-gon cylinder (r 15 mm, h 50 mm) with its top cap missing: a hole of 13 % of the surface."""
    m = trimesh.creation.cylinder(0.015, 0.05, sections=32)
    return trimesh.Trimesh(m.vertices, m.faces[m.face_normals[:, 2] < 0.5], process=False)


@pytest.fixture(scope="module")
def meshes(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("meshes")
    files = {"box": d / "box.obj", "cyl": d / "cyl.stl", "u": d / "u.ply", "blob": d / "blob.obj",
             "cup": d / "cup.ply"}
    trimesh.creation.box([0.06, 0.04, 0.02]).apply_translation([0.1, 0.2, 0.3]).export(files["box"])  # OBJ, m
    cyl = trimesh.creation.cylinder(0.015, 0.05, sections=32, transform=TILT)
    cyl.apply_scale(1000.0).export(files["cyl"])  # STL, mm, axis tilted away from the frame's axes
    u_channel().export(files["u"])
    pts = np.random.default_rng(3).uniform(-0.03, 0.03, (14, 3))  # convex, irregular: no symmetry
    trimesh.convex.convex_hull(pts).export(files["blob"])
    open_cylinder().export(files["cup"])
    return files


def _import(meshes: dict[str, Path], out: Path) -> int:
    names = ["box", "cyl", "u", "blob", "cup"]
    return main(["objects", "import", *[str(meshes[n]) for n in names], "--unit", "m", "mm", "m", "m", "m",
                 "--out", str(out), "--no-progress"])


@pytest.fixture(scope="module")
def imported(meshes, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("set") / "parts"
    assert _import(meshes, out) == 0
    return out


def _on_surface(mesh: trimesh.Trimesh, pts: np.ndarray, tol: float) -> bool:
    return float(trimesh.proximity.closest_point(mesh, pts)[1].max()) <= tol


@pytest.mark.slow
def test_import_measures_repairs_and_centres(imported: Path) -> None:
    objs = load_object_set(imported).by_name()
    assert list(objs) == ["box", "cyl", "u", "blob", "cup"]
    box = objs["box"]
    np.testing.assert_allclose(box.extents, [0.06, 0.04, 0.02], atol=1e-6)
    np.testing.assert_allclose(box.min_xyz, [-0.03, -0.02, -0.01], atol=1e-6)
    np.testing.assert_allclose(box.source["offset"], [-0.1, -0.2, -0.3], atol=1e-9)
    assert box.mass == pytest.approx(1050.0 * 0.06 * 0.04 * 0.02, rel=1e-6)
    assert box.diameter == pytest.approx(np.sqrt(0.06 ** 2 + 0.04 ** 2 + 0.02 ** 2), rel=1e-6)
    cyl = objs["cyl"]  # read in mm
    assert cyl.diameter == pytest.approx(np.hypot(0.03, 0.05), rel=1e-3)
    assert cyl.mass == pytest.approx(1050.0 * trimesh.creation.cylinder(0.015, 0.05, sections=32).volume, rel=1e-6)
    assert any("merged" in r for r in cyl.repairs)  # an STL is a triangle soup
    cup = objs["cup"]  # the missing cap was closed
    assert any("closed 1 hole" in r for r in cup.repairs)
    assert cup.volume == pytest.approx(trimesh.creation.cylinder(0.015, 0.05, sections=32).volume, rel=1e-6)
    for o in objs.values():
        np.testing.assert_allclose(o.vertices.min(0) + o.vertices.max(0), 0.0, atol=2e-6)  # bbox-centred
        assert not o.warnings, o.warnings  # every part suits the hand and the pick area
    R_up = trimesh.transformations.quaternion_matrix(objs["cyl"].upright_quat)[:3, :3]
    assert abs((R_up @ (TILT[:3, :3] @ [0, 0, 1.0]))[2]) < 1e-6  # the tilted cylinder is laid on its side ...
    assert not objs["cyl"].flat_bottom and not objs["cyl"].flat_top  # ... where it cannot stack
    assert objs["box"].flat_top and objs["box"].flat_bottom and np.allclose(objs["box"].upright_down, [0, 0, -1])
    assert not objs["u"].flat_top and objs["u"].flat_bottom


def test_collision_pieces_are_convex_and_cover_the_mesh(imported: Path) -> None:
    for o in load_object_set(imported).objects:
        mesh = trimesh.Trimesh(o.vertices, o.faces)
        hulls = []
        for p in o.collision:
            v = np.asarray(p["vertices"])
            hull = trimesh.convex.convex_hull(v)
            assert _on_surface(hull, v, 1e-7), f"{o.name}: a piece is not convex"
            hulls.append(hull)
        union = hulls[0] if len(hulls) == 1 else trimesh.boolean.union(hulls, engine="manifold")
        assert union.volume / mesh.volume == pytest.approx(1.0, abs=0.10), o.name
        pts = trimesh.sample.sample_surface(mesh, 300, seed=1)[0]
        inside = np.zeros(len(pts), bool)
        for h in hulls:
            inside |= (pts @ h.face_normals.T - np.sum(h.face_normals * h.triangles[:, 0], axis=1)).max(1) < 1e-4
        assert inside.mean() > 0.99, f"{o.name}: pieces leave {(~inside).mean():.1%} of the surface uncovered"
    objs = load_object_set(imported).by_name()
    assert len(objs["box"].collision) == len(objs["cyl"].collision) == 1  # convex: its own hull
    assert 2 <= len(objs["u"].collision) <= 32  # decomposed (CoACD), capped


def test_symmetries_found(imported: Path) -> None:
    objs = load_object_set(imported).by_name()
    (axis, offset), = objs["cyl"].symmetries_continuous
    assert abs(abs(axis @ (TILT[:3, :3] @ [0, 0, 1.0])) - 1) < 1e-6  # the cylinder's own (tilted) axis
    np.testing.assert_allclose(offset, 0.0, atol=1e-6)
    assert len(objs["cyl"].symmetries_discrete) == 1  # plus one flip, BOP style
    assert len(objs["box"].symmetries_discrete) == 3 and not objs["box"].symmetries_continuous
    for T in objs["box"].symmetries_discrete:  # half turns about the box's axes
        assert np.trace(T[:3, :3]) == pytest.approx(-1.0, abs=1e-6)
        assert np.allclose(np.abs(T[:3, :3]), np.round(np.abs(T[:3, :3])), atol=1e-6)
    assert len(objs["u"].symmetries_discrete) == 1 and not objs["u"].symmetries_continuous  # half turn about z
    assert not objs["blob"].symmetries_discrete and not objs["blob"].symmetries_continuous
    for o in objs.values():  # each symmetry maps the surface onto itself
        mesh = trimesh.Trimesh(o.vertices, o.faces)
        pts = trimesh.sample.sample_surface(mesh, 200, seed=2)[0]
        for T in o.symmetries_discrete:
            assert _on_surface(mesh, pts @ T[:3, :3].T + T[:3, 3], 0.01 * o.diameter), o.name


def test_the_shipped_blocks_symmetries_and_upright_faces_are_found() -> None:
    """On the eight blocks, the search (any frame) finds exactly the symmetries make_blocks.py found (axis-aligned),
    and the catalogue's upright face and stacking flags."""
    for block in load_catalog().values():
        mesh = trimesh.Trimesh(block.vertices, block.faces)
        props = mass_properties(mesh, 1050.0)
        up = upright(mesh, props.center_of_mass, 0.01 * props.diameter)
        assert np.allclose(up.down, block.upright_down), block.name
        assert (up.flat_top, up.flat_bottom) == (block.flat_top, block.flat_bottom), block.name
        found = find_symmetries(mesh, props.center_of_mass, props.inertia, 0.01 * props.diameter)
        disc, cont = found.discrete, found.continuous
        assert len(cont) == len(block.symmetries_continuous), block.name
        assert len(disc) == len(block.symmetries_discrete), block.name
        for T in disc:
            assert min(np.abs(T - S).max() for S in block.symmetries_discrete) < 1e-5, block.name


def test_the_fit_check_defaults_are_the_shipped_workcell() -> None:
    """The workcell the import checks parts against is the shipped one: the grasp settings' finger span, the
    workcell's pick area, hand camera and look height."""
    from posegrasp.grasping.config import GraspConfig
    from posegrasp.objects.config import FitCheckConfig
    from posegrasp.sim.config import load_workcell_config

    fit, g, w = FitCheckConfig(), GraspConfig(), load_workcell_config()
    assert fit.hand_span == (g.min_width, g.max_width)
    assert fit.pick_area_half_size == tuple(w.pick_area.half_size)
    assert (fit.camera_height, fit.camera_fovy_deg, fit.look_height) == \
        (w.hand_camera.height, w.hand_camera.fovy_deg, w.look_height)


@pytest.mark.slow
def test_same_input_gives_byte_identical_files(meshes, imported: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    assert _import(meshes, again) == 0
    assert snapshot(again) == snapshot(imported)


@pytest.mark.slow
def test_bop_models_folder_keeps_its_symmetries(imported: Path, tmp_path: Path) -> None:
    """A BOP models folder is read in mm and its models_info.json symmetries are taken, not searched."""
    models = tmp_path / "ds" / "models"
    models.mkdir(parents=True)
    info = json.loads((imported / "models" / "models_info.json").read_text())
    for i in (1, 2):
        shutil.copy(imported / "models" / f"obj_{i:06d}.ply", models)
    info = {"1": {**info["1"], "symmetries_discrete": info["1"]["symmetries_discrete"][:1]}, "2": info["2"]}
    (models / "models_info.json").write_text(json.dumps(info))
    out = tmp_path / "bopset"
    assert main(["objects", "import", str(models.parent), "--out", str(out), "--no-progress"]) == 0
    objs = load_object_set(out).objects
    assert [o.name for o in objs] == ["obj_000001", "obj_000002"]
    assert len(objs[0].symmetries_discrete) == 1 and "models_info.json" in objs[0].source["symmetries"]
    assert len(objs[1].symmetries_continuous) == 1


def test_show_draws_the_set(imported: Path, tmp_path: Path) -> None:
    png = tmp_path / "set.png"
    assert main(["objects", "show", str(imported), "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20000


def _bad_meshes(d: Path) -> dict[str, Path]:
    files = {"txt": d / "part.fbx", "empty": d / "empty.obj", "line": d / "line.obj", "cm": d / "big.stl",
             "lid": d / "lid.stl"}
    files["txt"].write_text("not a mesh\n")
    files["empty"].write_text("# no vertices\n")
    files["line"].write_text("v 0 0 0\nv 0.01 0 0\nv 0.02 0 0\nv 0.03 0 0\nf 1 2 3\nf 2 3 4\n")  # zero area
    trimesh.creation.box([6.0, 4.0, 2.0]).export(files["cm"])  # a 60 mm part in cm
    box = trimesh.creation.box([0.06, 0.04, 0.02])
    trimesh.Trimesh(box.vertices, box.faces[box.face_normals[:, 2] < 0.5]).export(files["lid"])  # top open: 37 %
    return files


@pytest.mark.parametrize("case, words", [
    ("missing", "no such file"), ("txt", "unknown mesh format '.fbx'"), ("empty", "no triangles"),
    ("line", "degenerate"), ("cm", "pass --unit cm"), ("lid", "too large to close"),
])
def test_bad_mesh_is_a_one_line_error_and_writes_nothing(capsys, tmp_path: Path, case: str, words: str) -> None:
    files = _bad_meshes(tmp_path)
    mesh = tmp_path / "nothere.stl" if case == "missing" else files[case]
    out = tmp_path / "set"
    refused(capsys, ["objects", "import", mesh, "--out", out, "--no-progress"], words)
    assert not out.exists() and not list(tmp_path.glob(".set*"))


def test_bad_set_folders_are_refused(capsys, imported: Path, tmp_path: Path) -> None:
    png = tmp_path / "x.png"
    refused(capsys, ["objects", "show", tmp_path / "none", "--out", png], "does not exist")
    ds = tmp_path / "ds"
    (ds / "models").mkdir(parents=True)
    (ds / "camera.json").write_text("{}")
    refused(capsys, ["objects", "show", ds, "--out", png], "is a BOP dataset, not an object set")
    broken = tmp_path / "broken"
    shutil.copytree(imported, broken)
    (broken / "objects" / "obj_000003.json").unlink()
    refused(capsys, ["objects", "show", broken, "--out", png], "obj_000003.json is missing")
    shutil.copytree(imported, broken, dirs_exist_ok=True)
    info = json.loads((broken / "models" / "models_info.json").read_text())
    info["2"]["size_x"] += 5.0
    (broken / "models" / "models_info.json").write_text(json.dumps(info))
    refused(capsys, ["objects", "show", broken, "--out", png], "does not match its models_info.json")
    shutil.rmtree(broken)
    shutil.copytree(imported, broken)
    man = json.loads((broken / "objectset.json").read_text())
    assert man["firm_hold_tasks"] == ["pick-place", "kitting", "stack"]
    man["firm_hold_tasks"] = "kitting"
    (broken / "objectset.json").write_text(json.dumps(man))
    refused(capsys, ["objects", "show", broken, "--out", png], "firm_hold_tasks must be a list of task names")
    before = snapshot(ds)
    refused(capsys, ["objects", "import", imported / "models" / "obj_000001.ply", "--out", ds], "not an object set")
    assert snapshot(ds) == before and not png.exists()


# --- settings files, symmetry groups and near symmetries -----------------------------------------------------------


def _box_file(d: Path) -> Path:
    path = d / "box.obj"
    trimesh.creation.box([0.06, 0.04, 0.02]).export(path)
    return path


@pytest.mark.parametrize("text, note", [
    ("[import]\ndensity = 2000.0\n\n[import.fit]\nhand_span = [0.012, 0.015]\n", False),  # as docs/objects.md
    ("density = 2000.0\n\n[fit]\nhand_span = [0.012, 0.015]\n", True),  # keys at the top level: read, with a note
])
def test_import_settings_file(capsys, tmp_path: Path, text: str, note: bool) -> None:
    cfg = tmp_path / "import.toml"
    cfg.write_text(text)
    out = tmp_path / "set"
    assert main(["objects", "import", str(_box_file(tmp_path)), "--out", str(out), "--config", str(cfg),
                 "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert ("[import] table" in err) == note and len(err.strip().splitlines()) == int(note), err
    o = load_object_set(out).objects[0]
    assert o.mass == pytest.approx(2000.0 * 0.06 * 0.04 * 0.02, rel=1e-6)
    assert any("exceeds the fingers' opening of 15.0 mm" in w for w in o.warnings), o.warnings


def test_the_documented_import_table_is_read(capsys, tmp_path: Path) -> None:
    """docs/objects.md's ``[import]`` sample is read as written, without a note."""
    from posegrasp.objects.config import load_import_config

    doc = (Path(__file__).resolve().parents[1] / "docs" / "objects.md").read_text(encoding="utf-8")
    sample = doc.split("```toml\n", 1)[1].split("```", 1)[0]
    cfg = tmp_path / "import.toml"
    cfg.write_text(textwrap.dedent(sample))
    read = load_import_config(cfg)
    assert (read.density, read.sym_tol_rel, read.step_linear_tolerance) == (2700.0, 0.015, 5e-5)
    assert read.fit.hand_span == (0.012, 0.085) and read.fit.look_height == 0.38  # the rest: the defaults
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("text, words", [
    ("[import]\ndensity = 2000.0\nmax_fold = 6\n[import.fit]\nlook_height = -1.0\n", "look_height = -1.0"),
    ("density = 2000.0\n[import]\nmax_fold = 6\n", "unknown section(s) ['density']"),
    ("[imports]\nmax_fold = 6\n", "unknown key(s) ['imports']"),
    ("[import]\nmin_size = 0.5\nmax_size = 0.1\n", "min_size = 0.5 m is not below max_size"),
])
def test_bad_import_settings_are_refused(capsys, tmp_path: Path, text: str, words: str) -> None:
    cfg = tmp_path / "import.toml"
    cfg.write_text(text)
    out = tmp_path / "set"
    refused(capsys, ["objects", "import", _box_file(tmp_path), "--out", out, "--config", cfg], words)
    assert not out.exists()


def truncated_icosahedron(radius: float) -> trimesh.Trimesh:
    """A soccer ball's polyhedron (60 vertices, 12 pentagons, 20 hexagons): its rotations are the icosahedral group
    of order 60."""
    ico = trimesh.creation.icosahedron()
    a, b = ico.vertices[ico.edges_unique].transpose(1, 0, 2)
    m = trimesh.convex.convex_hull(np.vstack([(2 * a + b) / 3, (a + 2 * b) / 3]))
    return m.apply_scale(radius / np.linalg.norm(m.vertices, axis=1).max())


def _closed(rotations: list[np.ndarray], angle: float = 1e-3) -> bool:
    """Whether ``rotations`` (3x3) and the identity are closed under composition, within ``angle`` rad."""
    group = np.array([np.eye(3), *rotations])
    return all(((np.einsum("kij,ij->k", group, A @ B) - 1) / 2).max() >= np.cos(angle) for A in group for B in group)


@pytest.mark.slow
def test_a_found_symmetry_set_is_a_group() -> None:
    """A soccer ball's turns about its 6 five-fold, 10 three-fold and 15 two-fold axes: 59 and the identity,
    closed under composition (the search's candidates alone miss the two-fold axes; closing the group finds them)."""
    ball = truncated_icosahedron(0.11).apply_transform(TILT)
    props = mass_properties(ball, 1050.0)
    found = find_symmetries(ball, props.center_of_mass, props.inertia, 0.01 * props.diameter)
    rotations = [T[:3, :3] for T in found.discrete]
    assert len(rotations) == 59 and not found.continuous and found.left_out == 0
    assert _closed(rotations)
    angles = np.round(np.degrees([np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)) for R in rotations]))
    assert sorted(np.unique(angles, return_counts=True)[1]) == [12, 12, 15, 20]  # 72, 144, 180, 120 deg


def test_turns_that_make_no_group_are_left_out() -> None:
    """Half turns about x and y that pass, whose product (the half turn about z) does not: the set keeps the first
    and leaves the second out, so it stays a group."""
    from posegrasp.objects.symmetry import _group

    class NoZ:  # passes every rotation but the half turn about z
        def passes(self, R: np.ndarray) -> bool:
            return not np.allclose(R, np.diag([-1.0, -1.0, 1.0]))

        def score(self, R: np.ndarray) -> float:
            return 0.0

    half_x, half_y = np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0])
    group, left_out = _group([half_x, half_y], NoZ(), 0.01, 60)
    assert len(group) == 1 and np.allclose(group[0], half_x) and left_out == 1


def bumped_box(height: float) -> trimesh.Trimesh:
    """A 60 x 40 x 20 mm box with a 10 x 10 mm pad ``height`` (m) high on its top near +x: its half turns move the
    pad about ``height`` off the surface."""
    box = trimesh.creation.box([0.06, 0.04, 0.02])
    pad = trimesh.creation.box([0.01, 0.01, height + 0.001], TF.translation_matrix([0.02, 0, 0.0095 + height / 2]))
    return trimesh.boolean.union([box, pad], engine="manifold")


def test_near_symmetries_are_reported_with_their_error(capsys, tmp_path: Path) -> None:
    """A pad 1.1 mm high (tolerance 0.75 mm): no symmetry, and the report names the three half turns and their
    surface error; the sym_tol_rel it names admits them."""
    mesh = bumped_box(0.0011)
    props = mass_properties(mesh, 1050.0)
    tol = 0.01 * props.diameter
    found = find_symmetries(mesh, props.center_of_mass, props.inertia, tol)
    assert not found.discrete and len(found.near) == 3
    assert all(tol < e <= 2 * tol and e == pytest.approx(0.0011, abs=2e-4) for _, e in found.near)
    assert all(np.trace(T[:3, :3]) == pytest.approx(-1.0, abs=1e-3) for T, _ in found.near)  # half turns
    lines = near_warnings(found, tol, props.diameter)
    assert len(lines) == 3 and all(" mm, over the 0.75 mm tolerance" in ln for ln in lines), lines
    need = max(float(ln.split("sym_tol_rel = ")[1].split()[0]) for ln in lines)
    assert len(find_symmetries(mesh, props.center_of_mass, props.inertia, need * props.diameter).discrete) == 3
    assert not find_symmetries(*_flat(0.0003)).near  # a pad within the tolerance: symmetric, nothing near
    mesh.export(tmp_path / "pad.ply")
    assert main(["objects", "import", str(tmp_path / "pad.ply"), "--out", str(tmp_path / "set"), "--no-progress"]) == 0
    shown = [ln for ln in capsys.readouterr().out.splitlines() if "near symmetry rejected: a 180 deg turn" in ln]
    assert len(shown) == 3 and load_object_set(tmp_path / "set").objects[0].warnings[-3:] == tuple(
        ln.removeprefix("  warning: ") for ln in shown)


def _flat(height: float) -> tuple:
    mesh = bumped_box(height)
    props = mass_properties(mesh, 1050.0)
    return mesh, props.center_of_mass, props.inertia, 0.01 * props.diameter
