"""Pile and bin scenes on the real simulator and renderer: parts dropped into the tote and settled, the same scene
for the same seed, a bin dataset whose visible fractions hold where parts hide parts and the walls hide parts,
table datasets as before, and bad input refused with one line."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from helpers import refused
from test_bad_input import snapshot

from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.bop.check import check_dataset
from posegrasp.cli import main
from posegrasp.catalog import load_catalog
from posegrasp.errors import SceneUnsettled
from posegrasp.geometry import rotation_angle, transform_points
from posegrasp.io import read_image
from posegrasp.perception.depth_render import DepthRenderer
from posegrasp.sim.clutter import ClutterConfig, build_clutter_scene, clutter_workcell, in_place, tote_of
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.scene import PALETTE, run_held
from posegrasp.sim.tote import tote_geoms
from posegrasp.sim.workcell import BlockInstance

CFG = ClutterConfig()
BIN_TOML = """
scene = "bin"
[workcell.hand_camera]
width = 320
height = 240
[depth_noise]
keep_clean = true
[distractors]
count = [0, 0]
"""


def scene(kind: str, n: int, seed: int, types: list[str] | None = None):
    """A settled clutter scene of ``n`` shipped blocks (cycling through ``types``, default all)."""
    cat = load_catalog("")
    names = types or list(cat)
    parts = [BlockInstance(cat[names[i % len(names)]], (*PALETTE[i % len(PALETTE)], 1.0)) for i in range(n)]
    wc = clutter_workcell(WorkcellConfig(), kind, parts, CFG)
    return wc, build_clutter_scene(wc, kind, CFG, seed)


@pytest.fixture(scope="module")
def bin12():
    return scene("bin", 12, 4)


def test_same_seed_same_scene_and_another_seed_another():
    _, a = scene("bin", 6, 1)
    _, b = scene("bin", 6, 1)
    _, c = scene("bin", 6, 2)
    assert [p.name for p, _ in a.parts] == [p.name for p, _ in b.parts]
    assert all(np.array_equal(Ta, Tb) for (_, Ta), (_, Tb) in zip(a.parts, b.parts))
    assert not all(np.allclose(Ta, Tc, atol=1e-3) for (_, Ta), (_, Tc) in zip(a.parts, c.parts))


def test_parts_settle_inside_the_tote_at_rest(bin12):
    wc, s = bin12
    tote = tote_of(wc.cfg, CFG)
    lo, hi = tote.inner_bounds()
    assert len(s.parts) == 12 and len({p.name for p, _ in s.parts}) == 8  # every shipped type, mixed
    for part, T in s.parts:
        v = transform_points(T, part.vertices)
        assert (v[:, :2] >= lo[:2] - 0.002).all() and (v[:, :2] <= hi[:2] + 0.002).all(), part.name
        assert v[:, 2].min() >= lo[2] - 0.002, part.name  # above the floor, not in it
    assert np.array_equal(np.array([T for _, T in s.parts]), wc.block_poses())
    P0 = wc.block_poses()
    run_held(wc, 0.5, lambda: False)  # half a second more moves nothing by more than the settle criterion
    P = wc.block_poses()
    assert np.linalg.norm(P[:, :3, 3] - P0[:, :3, 3], axis=1).max() < CFG.rest_motion[0]
    assert max(rotation_angle(a[:3, :3], b[:3, :3]) for a, b in zip(P, P0)) < np.deg2rad(CFG.rest_motion[1])
    assert wc.block_speeds().max(axis=0)[0] < 0.01


def test_tote_walls_collide_and_are_drawn(bin12):
    wc, _ = bin12
    ids = tote_geoms(wc.model)
    m = wc.model
    assert len(ids) == 5 and (m.geom_contype[ids] == 1).all() and (m.geom_conaffinity[ids] == 1).all()
    assert (m.geom_group[ids] < 3).all() and (m.geom_rgba[ids, 3] > 0).all()  # drawn by every renderer
    assert not wc.geom_instance[ids].any()  # never labelled


def test_a_pile_is_the_heap_without_walls():
    wc, s = scene("pile", 8, 3)
    assert not len(tote_geoms(wc.model)) and in_place(wc, "pile", CFG).all()
    z = np.array([T[2, 3] for _, T in s.parts])
    assert z.max() < 0.1  # on the table, settled


def test_a_heap_that_never_settles_is_dropped_again():
    """Three cylinders on the table, seed 6: on the first draw one lands on its side and rolls on (no rolling
    resistance), so with one draw the scene is unsettled; the next draw of the same generator settles."""
    cat = load_catalog("")
    parts = [BlockInstance(cat["cylinder"], (*PALETTE[i], 1.0)) for i in range(3)]
    one = dataclasses.replace(CFG, draws=1)
    with pytest.raises(SceneUnsettled, match="the last of 1 draws"):
        build_clutter_scene(clutter_workcell(WorkcellConfig(), "pile", parts, one), "pile", one, 6)
    wc = clutter_workcell(WorkcellConfig(), "pile", parts, CFG)
    build_clutter_scene(wc, "pile", CFG, 6)
    assert in_place(wc, "pile", CFG).all() and wc.block_speeds().max(axis=0)[0] < 0.01


@pytest.fixture(scope="module")
def bin_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bin")
    (root / "bin.toml").write_text(BIN_TOML)
    out = root / "ds"
    assert main(["datagen", "--out", str(out), "--config", str(root / "bin.toml"), "--scenes", "2", "--views", "3",
                 "--seed", "0", "--blocks", "14", "--workers", "1", "--no-progress"]) == 0
    return out


@pytest.mark.slow
def test_bin_dataset_passes_check_and_records_its_scene(bin_dataset):
    assert check_dataset(bin_dataset).ok
    info = json.loads((bin_dataset / "train_pbr" / "000000" / "scene_datagen.json").read_text())
    assert info["scene"] == "bin" and len(info["blocks"]) == 14
    config = json.loads((bin_dataset / "train_pbr" / "datagen_config.json").read_text())["config"]
    assert config["scene"] == "bin" and config["clutter"]["parts"] == [14, 14]
    gt = json.loads((bin_dataset / "train_pbr" / "000000" / "scene_gt.json").read_text())
    assert all(len(v) == 14 for v in gt.values())  # the parts only: the tote is no object of the dataset


def on_walls(mask: np.ndarray, depth: np.ndarray, camera: bop.SceneCamera) -> np.ndarray:
    """Which pixels of ``mask`` see (by ``depth``, m) a point of the tote's walls, within 2 mm."""
    v, u = np.nonzero(mask)
    z = depth[v, u]
    K = camera.K
    p_cam = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
    p = transform_points(np.linalg.inv(camera.T_cam_world), p_cam)
    lo, hi = tote_of(WorkcellConfig(), CFG).inner_bounds()
    t, tol = CFG.tote.thickness, 0.002
    inside_outer = np.all((p[:, :2] >= lo[:2] - t - tol) & (p[:, :2] <= hi[:2] + t + tol), axis=1)
    off_floor = np.any((p[:, :2] <= lo[:2] + tol) | (p[:, :2] >= hi[:2] - tol), axis=1)
    return inside_outer & off_floor & (p[:, 2] <= hi[2] + tol)


def test_visible_fractions_hold_under_parts_and_walls(bin_dataset):
    """BOP's visible fraction, re-measured independently: each part rendered alone by pyrender at its GT pose,
    its pixels visible where the scene's clean depth is not nearer; some are hidden by other parts, some by the
    tote's walls (the hiding surface back-projected onto them)."""
    cam = bop.load_camera(bin_dataset)
    W, H = cam.width, cam.height
    render = DepthRenderer({o: bop_models.load_model(bin_dataset, o) for o in bop.load_models_info(bin_dataset)})
    checked, under_parts, under_walls, fracts = 0, 0, 0, []
    for rec in bop.iter_scene_images(bin_dataset, "train_pbr"):
        clean = read_image(bop.image_path(rec.scene_dir, "depth_clean", rec.im_id)) * (rec.camera.depth_scale * 1e-3)
        parts = np.zeros((H, W), bool)
        for g in rec.instances:
            parts |= rec.load_mask(g.gt_index)
        for g in rec.instances:
            fracts.append(g.info.visib_fract)
            d = render(g.obj_id, g.T_cam_obj, rec.camera.K, H, W)
            sil = d > 0
            if sil.sum() < 100 or sil.sum() != g.info.px_count_all:
                continue  # small, or partly beyond the image
            seen = sil & (clean > 0) & (d - clean <= 0.003)
            assert abs(seen.sum() / sil.sum() - g.info.visib_fract) < 0.03, (rec.scene_id, rec.im_id, g.gt_index)
            hidden = sil & ~seen & (clean > 0)
            under_parts += (hidden & parts).sum() > 0.05 * sil.sum()
            under_walls += on_walls(hidden & ~parts, clean, rec.camera).sum() > 0.05 * sil.sum()
            checked += 1
    assert checked >= 30 and under_parts >= 3 and under_walls >= 1, (checked, under_parts, under_walls)
    assert min(fracts) < 0.5


def test_table_datasets_stay_as_they_were(tmp_path):
    """``--scene table`` is today's generation: same bytes as without the flag, and the record holds no pile or bin
    setting (a table dataset made before them resumes)."""
    base = ["--scenes", "1", "--views", "1", "--resolution", "64x48", "--blocks", "2", "--workers", "1",
            "--no-progress"]
    assert main(["datagen", "--out", str(tmp_path / "a"), *base]) == 0
    assert main(["datagen", "--out", str(tmp_path / "b"), "--scene", "table", *base]) == 0
    assert snapshot(tmp_path / "a") == snapshot(tmp_path / "b")
    config = json.loads((tmp_path / "a" / "train_pbr" / "datagen_config.json").read_text())["config"]
    assert not {"scene", "clutter", "clutter_views"} & set(config)
    assert "scene" not in json.loads((tmp_path / "a" / "train_pbr" / "000000" / "scene_datagen.json").read_text())


@pytest.mark.parametrize("argv, toml, words", [
    (["--scene", "heap"], "", "must be one of table, pile, bin"),
    (["--scene", "bin", "--blocks", "31"], "", "max_parts 30"),
    (["--scene", "pile", "--blocks", "20"], "[clutter.tote]\ninner_size = [0.1, 0.1]\n", "do not fit the tote"),
    (["--scene", "bin"], "[clutter.tote]\ninner_size = [0.07, 0.3]\n", "does not fit the tote's floor"),
    (["--scene", "bin"], "[clutter.tote]\ninner_size = [0.6, 0.8]\n", "cannot reach the tote's floor corner"),
    (["--scene", "bin"], "[clutter.tote]\nwall_height = 0.12\n", "cannot reach the tote's floor corner"),
])
def test_bad_clutter_input_is_refused_with_nothing_written(tmp_path, capsys, argv, toml, words):
    (tmp_path / "c.toml").write_text(toml)
    out = tmp_path / "o"
    refused(capsys, ["datagen", "--out", out, "--config", tmp_path / "c.toml", "--no-progress", *argv], words)
    assert snapshot(out) is None
