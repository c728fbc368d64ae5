"""Synthetic BOP dataset generation on the real simulator and renderer: labels, determinism, resuming, CLI.

One small dataset (2 scenes x 3 views at 320x240) is generated once per module and reused.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from matplotlib.path import Path as PolyPath
from scipy.spatial import ConvexHull

from helpers import cli, run_cli
from posegrasp.bop.check import CheckOptions, check_dataset
from posegrasp.datagen.config import load_datagen_config
from posegrasp.datagen.generate import STATS_FILE, generate_dataset, is_complete
from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.geometry import invert, transform_points
from posegrasp.io import read_image
from posegrasp.perception.depth_render import DepthRenderer

SEED, SCENES, VIEWS = 11, 2, 3
SMALL_TOML = """
blocks = [3, 5]
[workcell.hand_camera]
width = 320
height = 240
[depth_noise]
keep_clean = true
"""


def file_hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def small_toml(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("cfg") / "small.toml"
    p.write_text(SMALL_TOML)
    return p


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, small_toml) -> Path:
    """The reference dataset, generated in this process (one worker)."""
    out = tmp_path_factory.mktemp("ds") / "serial"
    generate_dataset(out, SCENES, VIEWS, SEED, load_datagen_config(small_toml), workers=1)
    return out


def records(root: Path) -> list[bop.ImageRecord]:
    return list(bop.iter_scene_images(root, "train_pbr"))


def backproject(depth: np.ndarray, K: np.ndarray, mask: np.ndarray) -> np.ndarray:
    v, u = np.nonzero(mask & (depth > 0))
    z = depth[v, u].astype(np.float64)
    return np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)


# ------------------------------------------------------------------------------------------- round trip

@pytest.mark.slow
def test_dataset_layout_and_check_passes(dataset):
    assert (dataset / "models" / "models_info.json").is_file() and (dataset / "camera.json").is_file()
    cam = bop.load_camera(dataset)
    assert (cam.width, cam.height) == (320, 240) and cam.depth_scale == 0.1
    assert bop.list_scenes(dataset, "train_pbr") == [0, 1]
    report = check_dataset(dataset, opts=CheckOptions(depth_tol_mm=3.0))
    assert report.ok, report.problems[:5]
    assert report.images == SCENES * VIEWS and sum(report.instances.values()) >= SCENES * VIEWS * 3
    assert np.median(report.depth_errors_mm) < 2.0  # the noisy depth, still on the models
    stats = json.loads((dataset / "train_pbr" / STATS_FILE).read_text())
    v = stats["views"]
    assert stats["images"] == SCENES * VIEWS == v["reached"]
    assert v["candidates"] == v["out_of_reach"] + v["unreachable"] + v["blocked"] + v["reached"]


@pytest.mark.slow
def test_check_compares_depth_inside_the_visible_outline(dataset, tmp_path):
    """Readings within INNER_PX of a visible mask's outline, where a sensor's lateral jitter measures the neighbours
    of a sliver of a part, do not count against the labels; a part whose inner depth is off is still caught."""
    import cv2
    import shutil

    from posegrasp.bop.check import INNER_PX

    root = Path(shutil.copytree(dataset, tmp_path / "copy"))
    rec = records(root)[0]
    inst = max(rec.instances, key=lambda g: rec.load_mask(g.gt_index).sum())
    visib = rec.load_mask(inst.gt_index)
    inner = cv2.erode(visib.astype(np.uint8), np.ones((2 * INNER_PX + 1,) * 2, np.uint8)) > 0
    path = bop.image_path(rec.scene_dir, "depth", rec.im_id)
    raw = read_image(path)
    opts = CheckOptions(depth_tol_mm=3.0)
    before = check_dataset(root, opts=opts)

    def nearer(where: np.ndarray) -> None:  # 20 mm nearer the camera at ``where``
        d = raw.copy()
        d[where & (d > 0)] -= np.uint16(round(20.0 / rec.camera.depth_scale))
        assert cv2.imwrite(str(path), d)

    nearer(visib & ~inner)
    after = check_dataset(root, opts=opts)
    assert after.ok and after.depth_errors_mm == before.depth_errors_mm
    nearer(inner)
    assert any(f"gt {inst.gt_index} (obj {inst.obj_id})" in p for p in check_dataset(root, opts=opts).problems)


def test_clean_depth_lies_on_models(dataset):
    checked = 0
    meshes = {}
    for rec in records(dataset):
        clean = read_image(bop.image_path(rec.scene_dir, "depth_clean", rec.im_id)) * (rec.camera.depth_scale * 1e-3)
        for g in rec.instances:
            pts = backproject(clean, rec.camera.K, rec.load_mask(g.gt_index))
            if len(pts) < 50:
                continue
            mesh = meshes.setdefault(g.obj_id, bop_models.load_model(dataset, g.obj_id))
            pts_obj = transform_points(invert(g.T_cam_obj), pts[:: max(1, len(pts) // 500)])
            _, dist, _ = trimesh.proximity.closest_point(mesh, pts_obj)
            assert np.median(dist) < 1e-3, (rec.scene_id, rec.im_id, g.obj_id, np.median(dist))
            checked += 1
    assert checked >= 10


def test_masks_and_info_agree(dataset):
    for rec in records(dataset):
        depth = rec.load_depth()
        for g in rec.instances:
            full, vis = rec.load_mask(g.gt_index, visible=False), rec.load_mask(g.gt_index)
            assert not (vis & ~full).any()  # amodal contains visible
            i = g.info
            x, y, w, h = i.bbox_obj
            inside = x >= 0 and y >= 0 and x + w < full.shape[1] and y + h < full.shape[0]
            assert i.px_count_visib == vis.sum() and i.px_count_all >= full.sum()
            assert i.px_count_all == full.sum() or not inside  # more: the silhouette beyond the image
            assert i.px_count_valid == (full & (depth > 0)).sum()
            assert i.visib_fract == (i.px_count_visib / i.px_count_all if i.px_count_all else 0.0)


def test_amodal_masks_are_exact_projections_of_convex_blocks(dataset):
    """The cube, long cuboid and prism are convex: their silhouette is the hull of the projected vertices."""
    checked = 0
    for rec in records(dataset):
        H, W = rec.load_depth().shape
        grid = np.stack(np.meshgrid(np.arange(W), np.arange(H)), axis=-1).reshape(-1, 2)
        for g in rec.instances:
            if g.obj_id not in (1, 2, 6):
                continue
            p = transform_points(g.T_cam_obj, bop_models.load_model(dataset, g.obj_id).vertices)
            uv = p[:, :2] / p[:, 2:] * rec.camera.K[[0, 1], [0, 1]] + rec.camera.K[:2, 2]
            exact = PolyPath(uv[ConvexHull(uv).vertices]).contains_points(grid).reshape(H, W)
            if exact.sum() < 100:  # (nearly) outside the image
                continue
            full = rec.load_mask(g.gt_index, visible=False)
            assert (exact & full).sum() / (exact | full).sum() > 0.995
            checked += 1
    assert checked >= 3


def test_amodal_masks_match_pyrender(dataset):
    """Each block rendered alone by pyrender (from the PLY model) at its GT pose gives its amodal mask."""
    cam_info = bop.load_camera(dataset)
    W, H = cam_info.width, cam_info.height
    render = DepthRenderer({o: bop_models.load_model(dataset, o) for o in bop.load_models_info(dataset)})
    ious = []
    for rec in records(dataset):
        for g in rec.instances:
            full = rec.load_mask(g.gt_index, visible=False)
            if full.sum() < 20:
                continue  # (nearly) out of view; occluded blocks are compared too: both render them alone
            sil = render(g.obj_id, g.T_cam_obj, rec.camera.K, H, W) > 0
            ious.append((sil & full).sum() / (sil | full).sum())
    assert len(ious) >= 10 and min(ious) >= 0.97 and np.mean(ious) > 0.99, ious


def test_gt_info_counts_the_whole_silhouette_as_bop_toolkit(dataset):
    """``px_count_all`` and ``bbox_obj`` cover each block's silhouette on a canvas 3x the image's size (bop_toolkit's
    ``calc_gt_info``), checked against pyrender there; boxes are [x, y, w, h] with w = x_max - x_min, empty: -1s."""
    cam = bop.load_camera(dataset)
    W, H = cam.width, cam.height
    render = DepthRenderer({o: bop_models.load_model(dataset, o) for o in bop.load_models_info(dataset)})
    beyond = 0
    for rec in records(dataset):
        K = rec.camera.K.copy()
        K[:2, 2] += (W, H)  # the image in the middle of the canvas
        for g in rec.instances:
            ys, xs = np.nonzero(render(g.obj_id, g.T_cam_obj, K, 3 * H, 3 * W) > 0)
            i = g.info
            if i.px_count_visib == 0:
                assert i.bbox_visib == bop.EMPTY_BOX
            if not len(xs):
                assert i.px_count_all == 0 and i.bbox_obj == bop.EMPTY_BOX
                continue
            assert abs(i.px_count_all - len(xs)) <= max(0.03 * len(xs), 5), (i, len(xs))
            box = (xs.min() - W, ys.min() - H, xs.max() - xs.min(), ys.max() - ys.min())
            assert np.abs(np.subtract(i.bbox_obj, box)).max() <= 1, (i.bbox_obj, box)
            beyond += not (W <= xs.min() and xs.max() < 2 * W and H <= ys.min() and ys.max() < 2 * H)
    assert beyond >= 1  # a block (partly) outside the image


def test_cameras_look_down_at_the_blocks_from_reachable_poses(dataset):
    for rec in records(dataset):
        T_world_cam = invert(rec.camera.T_cam_world)
        assert T_world_cam[2, 3] > 0.15 and T_world_cam[2, 2] < -0.3  # above the table, looking down
        assert max(g.info.px_count_visib for g in rec.instances) > 30  # the clutter is in view
        d = [np.linalg.norm(g.T_cam_obj[:3, 3]) for g in rec.instances if g.info.px_count_visib > 0]
        assert 0.15 < min(d) and max(d) < 1.0


def test_test_split_lists_bop19_targets_and_models_eval(dataset, tmp_path, small_toml):
    """A test split gets ``test_targets_bop19.json`` (instances >= 10 % visible) and the dataset ``models_eval/``
    (the models with edges of at most 5 % of their diameter, same surface); ``dataset check`` checks both."""
    out = tmp_path / "test"
    generate_dataset(out, 1, 2, SEED, load_datagen_config(small_toml), split="test", workers=1)
    recs = list(bop.iter_scene_images(out, "test"))
    assert bop.load_test_targets(out) == bop.targets_from_gt(recs) != []
    assert sum(t.inst_count for t in bop.load_test_targets(out)) == sum(
        g.info.visib_fract >= 0.1 for r in recs for g in r.instances)
    infos = bop.load_models_info(out)
    for o in infos:
        model, dense = bop_models.load_model(out, o), bop_models.load_model(bop.eval_model_path(out, o))
        assert bop.eval_model_path(out, o).parent.name == "models_eval" and len(dense.vertices) > len(model.vertices)
        assert dense.edges_unique_length.max() <= 0.05 * infos[o].diameter + 1e-9
        assert np.isclose(dense.area, model.area, rtol=1e-5) and np.allclose(dense.bounds, model.bounds, atol=1e-6)
    assert check_dataset(out).ok
    (out / bop.TEST_TARGETS_FILE).write_text('[{"scene_id": 0, "im_id": 0, "obj_id": 3, "inst_count": 7}]')
    assert any("'inst_count': expected" in p and p.endswith("got 7") for p in check_dataset(out).problems)


def test_check_flags_boxes_and_counts_against_bop_toolkit_rules(dataset, tmp_path):
    import shutil

    out = tmp_path / "old_rules"
    shutil.copytree(dataset, out)
    path = out / "train_pbr" / "000000" / "scene_gt_info.json"
    infos = json.loads(path.read_text())
    hidden = [g for v in infos.values() for g in v if g["px_count_visib"] == 0]
    seen = [g for v in infos.values() for g in v if 0 < g["px_count_all"] == g["px_count_visib"]]
    assert hidden and seen
    hidden[0]["bbox_visib"] = [-1, -1, 0, 0]  # the old empty box
    seen[0]["px_count_all"] -= 10  # a count clipped short of the mask
    path.write_text(json.dumps(infos))
    problems = "\n".join(check_dataset(out).problems)
    assert "of no pixel must be [-1, -1, -1, -1]" in problems and "px_count_all" in problems


# ------------------------------------------------------------------------------------------- determinism

@pytest.mark.slow
def test_same_bytes_with_two_workers(dataset, tmp_path, small_toml):
    out = tmp_path / "two"
    generate_dataset(out, SCENES, VIEWS, SEED, load_datagen_config(small_toml), workers=2)
    assert file_hashes(out) == file_hashes(dataset)


@pytest.mark.slow
def test_killed_run_resumes_to_the_same_bytes(dataset, tmp_path, small_toml):
    out = tmp_path / "killed"
    args = ["datagen", "--out", str(out), "--scenes", str(SCENES), "--views", str(VIEWS), "--seed", str(SEED),
            "--workers", "1", "--config", str(small_toml), "--no-progress"]
    proc = subprocess.Popen(cli(*args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    t0 = time.monotonic()
    while not is_complete(out, "train_pbr", 0):
        assert proc.poll() is None, proc.stderr.read().decode()
        assert time.monotonic() - t0 < 240, "first scene never completed"
        time.sleep(0.005)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not is_complete(out, "train_pbr", 1), "the run finished before it was killed"
    for p in out.rglob("*"):  # no partial files: everything but hidden temporaries is readable
        if p.is_file() and p.suffix == ".json":
            json.loads(p.read_text())
        elif p.is_file() and p.suffix in (".png", ".jpg") and not p.name.startswith("."):
            read_image(p)
    r = run_cli(*args)
    assert r.returncode == 0, r.stderr
    assert file_hashes(out) == file_hashes(dataset)
    r = run_cli(*args)
    assert r.returncode == 0 and "nothing to do" in r.stdout


def test_other_settings_are_refused_on_resume(dataset, tmp_path, small_toml):
    import shutil

    from posegrasp.errors import UserError

    out = tmp_path / "copy"
    shutil.copytree(dataset, out)
    with pytest.raises(UserError, match="other settings"):
        generate_dataset(out, SCENES, VIEWS, SEED + 1, load_datagen_config(small_toml), workers=1)


# ------------------------------------------------------------------------------------------- dataset check

@pytest.mark.slow
def test_check_names_corrupt_png_missing_key_and_metres(dataset, tmp_path):
    import shutil

    out = tmp_path / "broken"
    shutil.copytree(dataset, out)
    sd0, sd1 = out / "train_pbr" / "000000", out / "train_pbr" / "000001"
    mask = sd1 / "mask_visib" / "000001_000000.png"  # scene 1: scene 0's labels are unreadable
    mask.write_bytes(mask.read_bytes()[:40])
    gt = json.loads((sd0 / "scene_gt.json").read_text())
    del gt["2"][1]["cam_t_m2c"]
    (sd0 / "scene_gt.json").write_text(json.dumps(gt))
    gt = json.loads((sd1 / "scene_gt.json").read_text())
    gt["0"][0]["cam_t_m2c"] = [v / 1000.0 for v in gt["0"][0]["cam_t_m2c"]]
    (sd1 / "scene_gt.json").write_text(json.dumps(gt))
    cams = json.loads((sd1 / "scene_camera.json").read_text())
    cams["1"]["depth_scale"] = 1.0  # the png holds 0.1 mm units
    (sd1 / "scene_camera.json").write_text(json.dumps(cams))

    r = run_cli("dataset", "check", str(out))
    assert r.returncode == 1
    out_text = " ".join(r.stdout.split())
    assert "train_pbr/000001/mask_visib/000001_000000.png: expected an 8-bit single-channel PNG, got a truncated" \
        in out_text
    assert "train_pbr/000000/scene_gt.json: im 2 gt 1: expected a key 'cam_t_m2c'" in out_text
    assert "train_pbr/000001/scene_gt.json: im 0 gt 0: cam_t_m2c" in out_text and "looks like metres" in out_text
    assert "train_pbr/000001/depth/000001.png" in out_text and "depth_scale looks 10x too large" in out_text
    assert "problem" in out_text


def test_check_flags_models_in_metres(dataset, tmp_path):
    import shutil

    out = tmp_path / "models_m"
    shutil.copytree(dataset, out)
    info = json.loads((out / "models" / "models_info.json").read_text())
    info["3"]["diameter"] /= 1000.0
    (out / "models" / "models_info.json").write_text(json.dumps(info))
    report = check_dataset(out, opts=CheckOptions(max_images=1))
    assert any("models/models_info.json: obj 3 'diameter'" in p and "metres" in p for p in report.problems)


@pytest.mark.slow
def test_show_draws_a_panel(dataset, tmp_path):
    r = run_cli("dataset", "show", str(dataset), "--scene", "1", "--im", "2", "--out", str(tmp_path / "f.png"))
    assert r.returncode == 0, r.stderr
    img = read_image(tmp_path / "f.png")
    assert img.shape == (240, 640, 3)
    rgb = records(dataset)[-1].load_rgb()
    assert not np.array_equal(img[:, :320], rgb)  # labels drawn over the image


# ------------------------------------------------------------------------------------------- CLI input

@pytest.mark.parametrize("args, words", [
    (["datagen", "--out", "{tmp}/o", "--blocks", "0"], "--blocks"),
    (["datagen", "--out", "{tmp}/o", "--blocks", "6-2"], "MIN <= MAX"),
    (["datagen", "--out", "{tmp}/o", "--blocks", "99"], "do not fit"),
    (["datagen", "--out", "{tmp}/o", "--resolution", "wide"], "WIDTHxHEIGHT"),
    (["datagen", "--out", "{tmp}/o", "--scenes", "0"], "--scenes must be a positive integer"),
    (["datagen", "--out", "{tmp}/o", "--split", "val"], "invalid choice"),
    (["datagen", "--out", "{tmp}/o", "--config", "{tmp}/missing.toml"], "does not exist"),
    (["datagen", "--out", "{tmp}/o", "--config", "{tmp}/bad.toml"], "views.elevation_deg"),
    (["datagen", "--out", "{tmp}/o", "--config", "{tmp}/typo.toml"], "distractor"),
    (["dataset", "check", "{tmp}/nowhere"], "does not exist"),
    (["dataset", "show", "{tmp}/nowhere", "--scene", "0", "--im", "0", "--out", "{tmp}/x.png"], "does not exist"),
])
def test_bad_arguments_give_one_line(tmp_path, capsys, args, words):
    from posegrasp.cli import main

    (tmp_path / "bad.toml").write_text("[views]\nelevation_deg = [10.0, 95.0]\n")
    (tmp_path / "typo.toml").write_text("[distractor]\ncount = [1, 2]\n")
    rc = main([a.format(tmp=tmp_path) for a in args])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and words in err, err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_bad_arguments_exit_code_from_the_shell(tmp_path):
    r = run_cli("datagen", "--out", str(tmp_path / "o"), "--views", "many")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


def test_distractors_occlude_but_are_never_labelled():
    import dataclasses

    from posegrasp.datagen.config import DatagenConfig, DistractorConfig
    from posegrasp.datagen.render import LabelRenderer
    from posegrasp.datagen.scene import build_scene
    from posegrasp.geometry import look_at_R, make_T
    from posegrasp.sim.workcell import HAND_CAMERA

    cfg = DatagenConfig(blocks=(4, 4), distractors=DistractorConfig(count=(3, 3)))
    wc = build_scene(cfg, np.random.default_rng(2)).workcell
    ids = [i for i in range(wc.model.ngeom) if wc.model.geom(i).name.startswith("distractor_")]
    assert len(ids) == 3 and not wc.geom_instance[ids].any()
    for i in ids:  # look at a distractor from the arm's side
        target = wc.data.geom_xpos[i]
        toward_base = -target[:2] / np.linalg.norm(target[:2])
        pos = target + 0.4 * np.array([*(np.cos(np.pi / 4) * toward_base), np.sin(np.pi / 4)])  # 45 deg up
        q, dp, dr = wc.solve_camera_ik(make_T(look_at_R(target - pos), pos), wc.look_q)
        if dp < 5e-3 and dr < 0.02 and wc.drive_arm(q):
            break
    else:
        pytest.fail("no distractor could be looked at")
    c = dataclasses.replace(cfg.workcell.hand_camera, width=320, height=240)
    r = LabelRenderer(wc, HAND_CAMERA, c)
    with_d = r.capture()
    wc.model.geom_group[ids] = 5  # hidden from the renderer
    without = r.capture()
    r.close()
    drawn = with_d.depth < np.where(without.depth > 0, without.depth, np.inf)  # distractor pixels in front
    assert drawn.sum() > 100
    assert not with_d.mask[drawn].any()  # no label on a distractor
    for a, b in zip(with_d.extra["amodal"], without.extra["amodal"]):
        np.testing.assert_array_equal(a, b)  # amodal masks ignore them; visible ones lose what they hide
    assert all((with_d.mask == k).sum() <= (without.mask == k).sum() for k in range(1, 5))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("shape", [(1, 1), (3, 7), (480, 640)])
def test_grey_png_decodes_to_the_same_pixels(dtype, shape):
    """Depth and mask PNGs (``encode_grey_png``) read back bit for bit by OpenCV and Pillow (bop_toolkit's readers)."""
    import cv2
    from io import BytesIO

    from PIL import Image

    from posegrasp.bop.images import encode_grey_png

    rng = np.random.default_rng(shape[1])
    a = rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)
    a.flat[0], a.flat[-1] = np.iinfo(dtype).max, 0
    a[: shape[0] // 2] = 0  # long runs, as in masks and depth holes
    data = encode_grey_png(a)
    by_cv2 = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert by_cv2.dtype == dtype and np.array_equal(by_cv2, a)
    assert np.array_equal(np.asarray(Image.open(BytesIO(data))).astype(dtype), a)
    with pytest.raises(ValueError, match="float32"):
        encode_grey_png(a.astype(np.float32))
