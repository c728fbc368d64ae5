"""``posegrasp objects import`` on every format it reads, each part made by the test: a STEP cylinder written as
ISO-10303-21 B-rep text tessellates within 0.5 mm of the true surface; a URDF of two links (scaled, offset,
coloured) lands with its extents and colours; textures (GLB, OBJ+MTL) and vertex colours reach a dataset's images;
``--scale`` multiplies ``--unit``; bad input is one line with nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from helpers import refused

from posegrasp.cli import main
from posegrasp.errors import UserError
import posegrasp.objects.formats.urdf as urdf_format
from posegrasp.objset import load_object_set

R_MM, H_MM = 20.0, 30.0
CYAN, ORANGE = (30, 170, 210), (230, 120, 20)
YELLOWS = ((235, 200, 25), (205, 225, 25))


def cylinder_step(r: float, h: float) -> str:
    """ISO-10303-21 text of a solid cylinder in mm (axis z, base at z = 0): a closed shell of a cylindrical face
    bounded by two circles and a seam line, and two planar discs."""
    e: list[str] = []
    q = "''"

    def add(s: str) -> str:
        e.append(s)
        return f"#{len(e)}"

    def pt(x: float, y: float, z: float) -> str:
        return add(f"CARTESIAN_POINT('',({x:.6f},{y:.6f},{z:.6f}))")

    def oe(edge: str, same: str) -> str:
        return add(f"ORIENTED_EDGE('',*,*,{edge},{same})")

    def face(edges: list[str], surface: str, same: str) -> str:
        loop = add("EDGE_LOOP('',(" + ",".join(edges) + "))")
        return add(f"ADVANCED_FACE('',({add(f'FACE_OUTER_BOUND({q},{loop},.T.)')}),{surface},{same})")

    z, x = add("DIRECTION('',(0.,0.,1.))"), add("DIRECTION('',(1.,0.,0.))")
    ax0 = add(f"AXIS2_PLACEMENT_3D('',{pt(0, 0, 0)},{z},{x})")
    ax1 = add(f"AXIS2_PLACEMENT_3D('',{pt(0, 0, h)},{z},{x})")
    v0, v1 = add(f"VERTEX_POINT('',{pt(r, 0, 0)})"), add(f"VERTEX_POINT('',{pt(r, 0, h)})")
    e0 = add(f"EDGE_CURVE('',{v0},{v0},{add(f'CIRCLE({q},{ax0},{r:.6f})')},.T.)")
    e1 = add(f"EDGE_CURVE('',{v1},{v1},{add(f'CIRCLE({q},{ax1},{r:.6f})')},.T.)")
    line = add(f"LINE('',{pt(r, 0, 0)},{add(f'VECTOR({q},{z},{h:.6f})')})")
    seam = add(f"EDGE_CURVE('',{v0},{v1},{line},.T.)")
    side = face([oe(e0, ".T."), oe(seam, ".T."), oe(e1, ".F."), oe(seam, ".F.")],
                add(f"CYLINDRICAL_SURFACE('',{ax0},{r:.6f})"), ".T.")
    bottom = face([oe(e0, ".F.")], add(f"PLANE('',{ax0})"), ".F.")
    top = face([oe(e1, ".T.")], add(f"PLANE('',{ax1})"), ".T.")
    solid = add(f"MANIFOLD_SOLID_BREP('cylinder',{add(f'CLOSED_SHELL({q},({side},{bottom},{top}))')})")
    mm = add("( LENGTH_UNIT() NAMED_UNIT(*) SI_UNIT(.MILLI.,.METRE.) )")
    rad = add("( NAMED_UNIT(*) PLANE_ANGLE_UNIT() SI_UNIT($,.RADIAN.) )")
    sr = add("( NAMED_UNIT(*) SI_UNIT($,.STERADIAN.) SOLID_ANGLE_UNIT() )")
    unc = add(f"UNCERTAINTY_MEASURE_WITH_UNIT(LENGTH_MEASURE(1.E-07),{mm},'distance_accuracy_value','')")
    ctx = add(f"( GEOMETRIC_REPRESENTATION_CONTEXT(3) GLOBAL_UNCERTAINTY_ASSIGNED_CONTEXT(({unc})) "
              f"GLOBAL_UNIT_ASSIGNED_CONTEXT(({mm},{rad},{sr})) REPRESENTATION_CONTEXT('',''))")
    rep = add(f"ADVANCED_BREP_SHAPE_REPRESENTATION('',({ax0},{solid}),{ctx})")
    app = add("APPLICATION_CONTEXT('automotive design')")
    prod = add(f"PRODUCT('cylinder','cylinder','',({add(f'PRODUCT_CONTEXT({q},{app},{q})')}))")
    form = add(f"PRODUCT_DEFINITION_FORMATION('','',{prod})")
    dctx = add(f"PRODUCT_DEFINITION_CONTEXT('part definition',{app},'design')")
    pdef = add(f"PRODUCT_DEFINITION('design','',{form},{dctx})")
    add(f"SHAPE_DEFINITION_REPRESENTATION({add(f'PRODUCT_DEFINITION_SHAPE({q},{q},{pdef})')},{rep})")
    data = "\n".join(f"#{i}={s};" for i, s in enumerate(e, start=1))
    return ("ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION((''),'2;1');\nFILE_NAME('cylinder.step','',(''),(''),'','','');"
            "\nFILE_SCHEMA(('AUTOMOTIVE_DESIGN { 1 0 10303 214 1 1 1 1 }'));\nENDSEC;\nDATA;\n" + data
            + "\nENDSEC;\nEND-ISO-10303-21;\n")


def cylinder_distance(p: np.ndarray, r: float, h: float) -> np.ndarray:
    """Distance (m) of points ``p`` (N, 3) to the surface of the solid cylinder of radius ``r``, axis z, z in [0, h]."""
    rho, z = np.hypot(p[:, 0], p[:, 1]), p[:, 2]
    side = np.hypot(rho - r, np.maximum(0.0, np.maximum(-z, z - h)))
    out = np.maximum(0.0, rho - r)
    return np.minimum(side, np.minimum(np.hypot(out, z), np.hypot(out, z - h)))


def _import(paths: list[Path], out: Path, *extra: str) -> None:
    assert main(["objects", "import", *map(str, paths), "--out", str(out), "--no-progress", *extra]) == 0


def _step_deviation(tmp_path: Path, name: str, *extra: str) -> tuple[float, float, float]:
    """Max distance (m) of the imported cylinder's vertices and of surface samples to the true surface, and its
    volume over the true one."""
    step = tmp_path / "cylinder.step"
    step.write_text(cylinder_step(R_MM, H_MM))
    cfg = tmp_path / f"{name}.toml"
    cfg.write_text("[import]\n" + "\n".join(extra) + "\n")
    _import([step], tmp_path / name, "--config", str(cfg))
    o = load_object_set(tmp_path / name).objects[0]
    assert o.source["unit"] == "m" and o.source["file"] == "cylinder.step"
    mesh = trimesh.Trimesh(o.vertices, o.faces, process=False)
    shift = -np.asarray(o.source["offset"])  # object frame -> the file's frame (m)
    samples, _ = trimesh.sample.sample_surface(mesh, 20000, seed=0)
    r, h = R_MM / 1000, H_MM / 1000
    return (float(cylinder_distance(mesh.vertices + shift, r, h).max()),
            float(cylinder_distance(samples + shift, r, h).max()), mesh.volume / (np.pi * r * r * h))


@pytest.mark.slow
def test_a_step_cylinder_tessellates_within_half_a_millimetre(tmp_path: Path) -> None:
    v, s, vol = _step_deviation(tmp_path, "fine")
    assert v < 1e-5 and s < 0.5e-3 and vol == pytest.approx(1.0, abs=0.01), (v, s, vol)
    # the tolerance is the settings': a coarse one gives a coarser tessellation
    v, s_coarse, _ = _step_deviation(tmp_path, "coarse", "step_linear_tolerance = 0.005", "step_angular_tolerance = 1.0")
    assert v < 1e-5 and s_coarse > 0.5e-3 and s_coarse > 3 * s


def _urdf(d: Path) -> Path:
    """A 40 mm cube (a 10-unit STL scaled by 0.004, red) with a 20 mm knob on top (OBJ in metres, offset by a joint
    and its visual origin, a named blue material, found through package://)."""
    (d / "parts" / "meshes").mkdir(parents=True)
    trimesh.creation.box([10.0, 10.0, 10.0]).export(d / "parts" / "meshes" / "body.stl")
    trimesh.creation.cylinder(0.01, 0.02, sections=48).export(d / "parts" / "meshes" / "knob.obj")
    urdf = d / "parts" / "knobbed.urdf"
    urdf.write_text("""<?xml version="1.0"?>
<robot name="knobbed">
  <material name="blue"><color rgba="0.1 0.2 0.9 1"/></material>
  <link name="body">
    <visual><geometry><mesh filename="meshes/body.stl" scale="0.004 0.004 0.004"/></geometry>
      <material name="red"><color rgba="0.9 0.1 0.1 1"/></material></visual>
    <collision><geometry><box size="1 1 1"/></geometry></collision>
  </link>
  <link name="knob">
    <visual><origin xyz="0 0 0.02" rpy="0 0 0"/>
      <geometry><mesh filename="package://parts/meshes/knob.obj"/></geometry><material name="blue"/></visual>
  </link>
  <joint name="fix" type="fixed"><parent link="body"/><child link="knob"/><origin xyz="0 0 0.01"/></joint>
</robot>
""")
    return urdf


def test_a_urdf_lands_with_its_links_scales_offsets_and_colours(tmp_path: Path) -> None:
    _import([_urdf(tmp_path)], tmp_path / "set")
    o = load_object_set(tmp_path / "set").objects[0]
    assert np.asarray(o.extents) == pytest.approx([0.04, 0.04, 0.06], abs=1e-6)
    assert o.volume == pytest.approx(0.04 ** 3 + np.pi * 0.01 ** 2 * 0.02, rel=0.01)
    s = o.surface
    h, w = s.image.shape[:2]
    px = s.image[np.clip(((1 - s.uv[:, 1]) * h).astype(int), 0, h - 1), np.clip((s.uv[:, 0] * w).astype(int), 0, w - 1)]
    top = s.vertices[:, 2] > o.min_xyz[2] + 0.04 + 1e-6  # the knob's vertices (object frame)
    assert top.any() and (~top).any()
    assert (px[top] == np.round(np.array([0.1, 0.2, 0.9]) * 255)).all()
    assert (px[~top & (s.vertices[:, 2] < o.min_xyz[2] + 0.04 - 1e-6)] == np.round(np.array([0.9, 0.1, 0.1]) * 255)).all()


def _textured_box(size: list[float], colour: tuple[int, int, int], seed: int) -> trimesh.Trimesh:
    """A box mapped into the top half of its texture, ``colour`` with a faint checker; the bottom half is magenta
    (an image upside down shows magenta)."""
    img = np.tile(np.array(colour, np.uint8), (32, 32, 1))
    img[:8, :16] = np.clip(img[:8, :16].astype(int) - 12, 0, 255)
    img[16:] = (220, 20, 220)
    box = trimesh.creation.box(size)
    uv = np.random.default_rng(seed).uniform(0.55, 0.95, (len(box.vertices), 2))  # v up: the image's top half
    return trimesh.Trimesh(box.vertices, box.faces, process=False,
                            visual=trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(img)))


@pytest.fixture(scope="module")
def looks(tmp_path_factory) -> Path:
    """A set of a textured GLB (cyan), an OBJ+MTL with a texture (orange) and a PLY with two yellows per vertex."""
    d = tmp_path_factory.mktemp("looks")
    _textured_box([0.05, 0.035, 0.025], CYAN, 0).export(d / "cyan.glb")
    (d / "obj").mkdir()
    _textured_box([0.045, 0.04, 0.03], ORANGE, 1).export(d / "obj" / "orange.obj")
    vc = trimesh.creation.box([0.05, 0.04, 0.03])
    vc.visual.vertex_colors = [(*YELLOWS[int(v[2] > 0)], 255) for v in vc.vertices]
    vc.export(d / "yellow.ply")
    assert (d / "obj" / "material.mtl").is_file() and list((d / "obj").glob("*.png"))
    _import([d / "cyan.glb", d / "obj" / "orange.obj", d / "yellow.ply"], d / "set")
    return d


def test_textures_and_vertex_colours_are_kept_in_the_set(looks: Path) -> None:
    objs = load_object_set(looks / "set").by_name()
    for name, colour in (("cyan", CYAN), ("orange", ORANGE), ("yellow", np.mean(YELLOWS, axis=0))):
        o = objs[name]
        assert o.surface is not None and o.rgba == (1.0, 1.0, 1.0, 1.0)
        top = o.surface.image[: o.surface.image.shape[0] // 2] if name != "yellow" else o.surface.image
        assert np.abs(top.reshape(-1, 3).mean(axis=0) - colour).max() < 12, name
        # the surface lies on the model (object frame)
        assert np.abs(o.surface.vertices.min(axis=0) - o.min_xyz).max() < 1e-9
        assert (looks / "set" / "objects" / f"obj_{o.obj_id:06d}_texture.png").is_file()


def test_a_dataset_shows_the_textures_in_the_parts_masks(looks: Path, tmp_path: Path) -> None:
    ds = tmp_path / "ds"
    assert main(["datagen", "--out", str(ds), "--objects", str(looks / "set"), "--scenes", "2", "--views", "2",
                 "--resolution", "160x120", "--blocks", "3", "--rgb-format", "png", "--workers", "1",
                 "--no-progress"]) == 0
    want = {1: CYAN, 2: ORANGE, 3: tuple(np.mean(YELLOWS, axis=0))}
    seen: dict[int, int] = {}
    for scene in sorted((ds / "train_pbr").glob("0*")):
        gt = json.loads((scene / "scene_gt.json").read_text())
        for view, insts in gt.items():
            rgb = np.asarray(Image.open(scene / "rgb" / f"{int(view):06d}.png").convert("RGB"), np.float64)
            for k, inst in enumerate(insts):
                mask = np.asarray(Image.open(scene / "mask_visib" / f"{int(view):06d}_{k:06d}.png")) > 0
                if mask.sum() < 40:
                    continue
                mean = rgb[mask].mean(axis=0)
                ref = np.asarray(want[inst["obj_id"]], np.float64)
                cos = mean @ ref / np.linalg.norm(mean) / np.linalg.norm(ref)  # lighting scales, hue stays
                assert cos > 0.97, (inst["obj_id"], mean, ref)
                seen[inst["obj_id"]] = seen.get(inst["obj_id"], 0) + 1
    assert len(seen) >= 2, seen
    assert main(["dataset", "check", str(ds)]) == 0


def test_scale_multiplies_the_unit(tmp_path: Path) -> None:
    trimesh.creation.box([0.5, 0.4, 0.3]).export(tmp_path / "decimetres.obj")
    _import([tmp_path / "decimetres.obj"], tmp_path / "set", "--scale", "0.1")
    o = load_object_set(tmp_path / "set").objects[0]
    assert np.asarray(o.extents) == pytest.approx([0.05, 0.04, 0.03], abs=1e-9) and o.source["scale"] == 0.1
    _import([tmp_path / "decimetres.obj"], tmp_path / "set2", "--unit", "cm", "--scale", "10")
    assert np.asarray(load_object_set(tmp_path / "set2").objects[0].extents) == pytest.approx([0.05, 0.04, 0.03])


def test_obj_naming_a_missing_material_library_is_read_without_it(tmp_path: Path) -> None:
    """Public assets ship OBJs whose ``mtllib`` is not in the package (pybullet_data's lego.obj, cube.obj): the
    geometry imports, the warning names the file; a URDF colour stands in for the materials without a warning."""
    text = trimesh.creation.box([0.05, 0.04, 0.03]).export(file_type="obj")
    (tmp_path / "brick.obj").write_text("mtllib brick.mtl\nusemtl yellow\n" + text)
    (tmp_path / "brick.urdf").write_text("""<?xml version="1.0"?>
<robot name="brick"><link name="base"><visual><geometry><mesh filename="brick.obj"/></geometry>
<material name="y"><color rgba="1 1 0.4 1"/></material></visual></link></robot>""")
    _import([tmp_path / "brick.obj", tmp_path / "brick.urdf"], tmp_path / "set", "--name", "obj", "urdf")
    obj, urdf = load_object_set(tmp_path / "set").objects
    assert np.asarray(obj.extents) == pytest.approx([0.05, 0.04, 0.03], abs=1e-9)
    assert [w for w in obj.warnings if "material library 'brick.mtl'" in w]
    assert urdf.warnings == () and urdf.rgba == pytest.approx((1.0, 1.0, 0.4, 1.0), abs=0.003)


def test_urdf_without_visuals_is_its_collision_shape(tmp_path: Path) -> None:
    (tmp_path / "ball.urdf").write_text("""<?xml version="1.0"?>
<robot name="ball"><link name="base"><collision><origin xyz="0.1 0 0"/><geometry><sphere radius="0.02"/></geometry>
</collision></link></robot>""")
    _import([tmp_path / "ball.urdf"], tmp_path / "set")
    o = load_object_set(tmp_path / "set").objects[0]
    assert np.asarray(o.extents) == pytest.approx([0.04, 0.04, 0.04], abs=1e-3)
    assert [w for w in o.warnings if "no visual geometry: its collision geometry" in w]


def _bad(d: Path) -> dict[str, list[str]]:
    (d / "notex").mkdir()
    _textured_box([0.05, 0.04, 0.03], ORANGE, 2).export(d / "notex" / "part.obj")
    for png in (d / "notex").glob("*.png"):
        png.unlink()
    urdf = _urdf(d)
    (urdf.parent / "meshes" / "knob.obj").unlink()
    (d / "corrupt.step").write_text("ISO-10303-21;\nHEADER;\nENDSEC;\nDATA;\n#1=CARTESIAN_POINT('',(0.,0.,\n")
    (d / "text.stp").write_text("not a step file\n")
    (d / "box.stl").write_bytes(trimesh.creation.box([0.05, 0.04, 0.03]).export(file_type="stl"))
    box = str(d / "box.stl")
    return {"texture": [str(d / "notex" / "part.obj")], "urdf": [str(urdf)], "corrupt": [str(d / "corrupt.step")],
            "text": [str(d / "text.stp")], "zero": [box, "--scale", "0"], "negative": [box, "--scale", "-1"],
            "nan": [box, "--scale", "nan"], "count": [box, "--scale", "1", "2"]}


@pytest.mark.parametrize("case, words", [
    ("texture", "names 'material_0.png', which is not in"), ("urdf", "mesh 'package://parts/meshes/knob.obj' not found"),
    ("corrupt", "could not read a solid"), ("text", "not a STEP file"), ("zero", "--scale must be a finite number > 0"),
    ("negative", "--scale must be a finite number > 0"), ("nan", "--scale must be a finite number > 0"),
    ("count", "give one finite factor > 0 for all meshes, or one per mesh"),
])
def test_bad_input_is_one_line_and_writes_nothing(capsys, tmp_path: Path, case: str, words: str) -> None:
    args = _bad(tmp_path)[case]
    out = tmp_path / "set"
    refused(capsys, ["objects", "import", *args, "--out", out, "--no-progress"], words)
    assert not out.exists() and not list(tmp_path.glob(".set*"))



def test_urdf_meshes_resolve_under_the_root_the_user_names_and_never_outside_it(capsys, tmp_path: Path) -> None:
    """A robot package's URDF in ``pkg/urdf/`` naming ``package://parts/...`` of another package in the workspace:
    found under ``--mesh-root`` (the workspace), refused without it; a path climbing out of the root is refused."""
    (tmp_path / "ws" / "parts" / "meshes").mkdir(parents=True)
    trimesh.creation.box([0.02, 0.02, 0.02]).export(tmp_path / "ws" / "parts" / "meshes" / "body.stl")
    trimesh.creation.box([0.02, 0.02, 0.02]).export(tmp_path / "outside.stl")
    (tmp_path / "ws" / "robot" / "urdf").mkdir(parents=True)
    urdf = tmp_path / "ws" / "robot" / "urdf" / "part.urdf"

    def with_mesh(name: str) -> Path:
        urdf.write_text(f'<robot name="p"><link name="b"><visual><geometry><mesh filename="{name}"/></geometry>'
                        '</visual></link></robot>')
        return urdf

    with pytest.raises(UserError, match="not found under"):
        urdf_format.read(with_mesh("package://parts/meshes/body.stl"))
    part = urdf_format.read(urdf, tmp_path / "ws")
    assert np.asarray(part.mesh.extents) == pytest.approx([0.02] * 3)
    for name in ("../../../outside.stl", str(tmp_path / "outside.stl"), "package://../../outside.stl"):
        with pytest.raises(UserError, match="not found under"):
            urdf_format.read(with_mesh(name), tmp_path / "ws")
    refused(capsys, ["objects", "import", urdf, "--mesh-root", tmp_path / "nowhere", "--out", tmp_path / "set"],
            "--mesh-root")
    assert not (tmp_path / "set").exists()


def test_opencascades_messages_stay_off_the_terminal_and_its_error_is_in_ours(capfd, tmp_path: Path) -> None:
    import posegrasp.objects.formats.step as step_format

    bad = tmp_path / "corrupt.step"
    bad.write_text("ISO-10303-21;\nHEADER;\nENDSEC;\nDATA;\n#1=CARTESIAN_POINT('',(0.,0.,\n")
    with pytest.raises(UserError, match="could not read a solid .*Undefined Parsing"):
        step_format.read(bad, 1e-4, 0.5)
    out, err = capfd.readouterr()
    assert "StepFile" not in out + err and "Failed to read" not in out + err, out + err
