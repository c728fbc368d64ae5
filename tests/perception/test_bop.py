"""BOP reading/writing: units at the boundary, round trips, results CSV."""

import json

import numpy as np
import pytest
from bop_helpers import read_results_csv

from posegrasp import bop
from posegrasp.bop import results as bop_results
from posegrasp.bop import models as bop_models
from posegrasp.bop import images as bop_images
from posegrasp.errors import UserError
from posegrasp.geometry import axis_angle_R, make_T


def test_tiny_dataset_reads_in_metres(tiny_bop):
    cam = bop.load_camera(tiny_bop)
    assert (cam.width, cam.height, cam.depth_scale) == (160, 120, 0.1)
    infos = bop.load_models_info(tiny_bop)
    assert sorted(infos) == [1, 2, 3]
    assert not infos[1].symmetric and infos[2].symmetric and infos[3].symmetric
    assert infos[3].diameter == pytest.approx(np.sqrt(0.06 ** 2 + 0.03 ** 2 + 0.02 ** 2))
    raw = json.loads(bop.models_info_path(tiny_bop).read_text())
    assert raw["3"]["diameter"] == pytest.approx(infos[3].diameter * 1000)  # mm on disk
    mesh = bop_models.load_model(tiny_bop, 3)
    np.testing.assert_allclose(mesh.extents, [0.06, 0.03, 0.02], atol=1e-9)
    recs = list(bop.iter_scene_images(tiny_bop, "train"))
    assert len(recs) == 8 and all(len(r.instances) == 3 for r in recs)
    r = recs[0]
    depth = r.load_depth()
    assert depth.dtype == np.float32 and 0.25 < depth[depth > 0].min() < depth.max() < 0.7
    for g in r.instances:
        assert 0.3 <= g.T_cam_obj[2, 3] <= 0.6  # metres
        m = r.load_mask(g.gt_index)
        assert m.dtype == bool and m.sum() == g.info.px_count_visib
    assert r.rgb_path.exists() and r.load_rgb().shape == (120, 160, 3)


def test_model_arrays_are_trimeshs_numbers_with_or_without_it(tmp_path):
    import trimesh

    from posegrasp import ASSETS

    files = sorted((ASSETS / "blocks" / "models").glob("*.ply"))
    mesh = trimesh.load(files[0], force="mesh", process=False)
    files.append(tmp_path / "ascii.ply")  # a layout read by trimesh
    files[-1].write_bytes(mesh.export(file_type="ply", encoding="ascii"))
    for p in files:
        v, f = bop_models.model_arrays(p)
        want = trimesh.load(p, force="mesh", process=False)
        want.apply_scale(bop.MM)
        assert (bop_models.plain_ply(p.read_bytes()) is None) == (p.parent == tmp_path)
        assert v.tobytes() == np.asarray(want.vertices, np.float64).tobytes()  # bit for bit, zeros' signs too
        assert f.tobytes() == np.asarray(want.faces, np.int64).tobytes()
    cut = tmp_path / "cut.ply"
    cut.write_bytes(files[0].read_bytes()[:-7])
    with pytest.raises(UserError, match="cut.ply: expected a PLY triangle mesh, got an unreadable file"):
        bop_models.model_arrays(cut)


def test_eval_models_are_trimeshs_edges_and_files_byte_for_byte():
    import trimesh

    meshes = [trimesh.creation.box((0.03, 0.02, 0.05)), trimesh.creation.cylinder(0.02, 0.05, sections=24),
              trimesh.creation.icosphere(2, 0.03), trimesh.creation.annulus(0.01, 0.02, 0.03)]
    for m in meshes:
        edges, fe = bop_models.unique_edges(m.faces)
        assert np.array_equal(edges, m.edges_unique) and np.array_equal(fe, m.faces_unique_edges)
        v, f = bop_models.resample_for_eval(m.vertices, m.faces, 0.004)
        assert bop_models.ply_bytes(v, f) == trimesh.Trimesh(v, f, process=False).export(file_type="ply",
                                                                                         encoding="binary")
        assert np.array_equal(bop_models.plain_ply(bop_models.ply_bytes(v, f))[1], f)


def test_an_object_set_is_read_without_importing_trimesh():
    import subprocess
    import sys

    code = "import sys; from posegrasp.catalog import load_catalog; load_catalog(''); print('trimesh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False"]


def test_scene_round_trip(tmp_path):
    T = make_T(axis_angle_R(np.array([1.0, 2.0, 3.0]), 0.7), np.array([0.01, -0.02, 0.5]))
    bop.write_scene_gt(tmp_path / "scene_gt.json", {3: [(7, T)]})
    raw = json.loads((tmp_path / "scene_gt.json").read_text())
    assert raw["3"][0]["cam_t_m2c"] == pytest.approx([10.0, -20.0, 500.0])
    back = bop.load_scene_gt(tmp_path / "scene_gt.json")
    assert back[3][0][0] == 7 and np.allclose(back[3][0][1], T, atol=1e-12)
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    bop.write_scene_camera(tmp_path / "scene_camera.json", {3: bop.SceneCamera(K, 0.1, T)})
    c = bop.load_scene_camera(tmp_path / "scene_camera.json")[3]
    assert np.allclose(c.K, K) and c.depth_scale == 0.1 and np.allclose(c.T_cam_world, T)
    info = bop.GTInfo((1, 2, 3, 4), (1, 2, 3, 3), 12, 11, 9, 0.75)
    bop.write_scene_gt_info(tmp_path / "scene_gt_info.json", {3: [info]})
    assert bop.load_scene_gt_info(tmp_path / "scene_gt_info.json")[3] == [info]
    d = np.array([[0.0, 0.5, 1.23456]])
    assert np.array_equal(bop_images.depth_to_png(d, 0.1), [[0, 5000, 12346]])


def test_results_csv(tmp_path):
    T = make_T(axis_angle_R(np.array([0.0, 0.0, 1.0]), 0.3), np.array([0.1, 0.2, 0.3]))
    p = bop_results.write_results_csv(tmp_path / "res.csv", [bop_results.PoseResult(1, 2, 3, 0.5, T, 0.25)])
    lines = p.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    assert lines[1].split(",")[5] == "100 200 300"
    assert len(lines[1].split(",")[4].split()) == 9
    back = read_results_csv(p)[0]
    assert np.array_equal(back.T_cam_obj, T) and back.score == 0.5 and back.time == 0.25  # lossless


def test_missing_files_are_user_errors(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        bop.load_models_info(tmp_path)
    with pytest.raises(UserError, match="does not exist"):
        list(bop.iter_scene_images(tmp_path, "test"))
    (tmp_path / "camera.json").write_text("{not json")
    with pytest.raises(UserError, match="camera.json: expected valid JSON"):
        bop.load_camera(tmp_path)
