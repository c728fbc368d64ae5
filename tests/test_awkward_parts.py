"""Parts of awkward shapes from public object libraries. Thin parts (a 6.4 mm domino) come to rest on the table:
their collision pieces get contacts stiff enough that a drop does not sink them past half their thickness (then
MuJoCo pushes them through the table or blows up); lying flat, they are pinched low enough for the fingertips to
grip their edges, and picked. A sphere's symmetry is three orthogonal continuous axes, sampled so that grasp
planning stays quick."""

from __future__ import annotations

import json
import time
from pathlib import Path

import mujoco
import numpy as np
import pytest
import trimesh

from posegrasp.catalog import load_catalog, symmetry_transforms
from posegrasp.cli import main
from posegrasp.datagen.scene import stack_drops
from posegrasp.geometry import make_T
from posegrasp.grasping.config import GraspConfig
from posegrasp.grasping.grasps import plan_grasps
from posegrasp.grasping.hand import FLAT_PINCH_DROP
from posegrasp.sim.config import WorkcellConfig, with_objects
from posegrasp.sim.scene import SceneConfig, choose_types, drop_poses, make_scene, settle
from posegrasp.sim.workcell import CONTACT_TIMECONST, BlockInstance, Workcell, contact_timeconst, thickness

DOMINO = (0.0064, 0.0254, 0.0508)  # m: pybullet_data's domino


@pytest.fixture(scope="module")
def dominoes(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("thin")
    trimesh.creation.box(DOMINO).export(d / "domino.obj")
    assert main(["objects", "import", str(d / "domino.obj"), "--out", str(d / "set"), "--no-progress"]) == 0
    return d / "set"


def test_contact_time_constant_follows_the_thinnest_width():
    box = trimesh.creation.box(DOMINO)
    box.apply_transform(trimesh.transformations.random_rotation_matrix(np.random.default_rng(0).random(3)))
    assert thickness(box.vertices) == pytest.approx(0.0064)
    assert contact_timeconst(0.018, 0.002) == pytest.approx(np.e * 0.018 / 8)
    assert contact_timeconst(0.0064, 0.002) == pytest.approx(0.006)  # never under three physics steps
    assert contact_timeconst(0.0237, 0.002) == CONTACT_TIMECONST  # the shipped blocks keep MuJoCo's default


def test_dropped_dominoes_rest_on_the_table(dominoes):
    wcfg = with_objects(WorkcellConfig(), dominoes)
    cfg = SceneConfig(workcell=wcfg)
    for seed in range(6):
        rng = np.random.default_rng(seed)
        types = choose_types(cfg, 3, rng)
        wc = Workcell(wcfg, [BlockInstance(t, (1.0, 0.0, 0.0, 1.0)) for t in types])
        assert wc.model.geom_solref[wc.model.geom("block_1_col0").id][0] == pytest.approx(0.006)
        for k, T in enumerate(drop_poses(cfg, types, rng), start=1):
            wc.set_block_pose(k, T)
        mujoco.mj_forward(wc.model, wc.data)
        settle(wc, cfg)
        z = wc.block_poses()[:, 2, 3]
        # lying flat (3.2 mm) or on one another (12.7 mm on the one below); never sunk into or through the table
        assert np.all((z > 0.0025) & (z < 0.015)), (seed, z)
        assert wc.data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number == 0, seed
    for seed in range(3):  # and the scenes of scene, datagen and trials settle
        z = make_scene(seed, 3, cfg).workcell.block_poses()[:, 2, 3]
        assert np.all((z > 0.0025) & (z < 0.015)), (seed, z)


@pytest.mark.slow
def test_a_flat_domino_is_pinched_low_and_picked(dominoes, tmp_path):
    """Lying flat, its top 6.4 mm up, below the lowest pinch height: pinched ``FLAT_PINCH_DROP`` lower, where the
    fingertips grip its edges (at the lowest pinch height 5 of these 8 episodes slipped out of the fingers)."""
    cfg = GraspConfig()
    domino = load_catalog(dominoes)["domino"]
    thin = int(np.argmin(domino.extents))
    R = np.eye(3)[:, [(j - thin + 2) % 3 for j in range(3)]]  # the thin axis up
    lying = make_T(R, (0.45, 0.0, -(domino.vertices @ R.T)[:, 2].min()))
    grasps = plan_grasps(domino, lying, np.zeros((0, 3)), cfg, yaw_now=0.0)
    assert grasps and {round(g.T_world_gripper[2, 3], 4) for g in grasps} == {cfg.min_pinch_height - FLAT_PINCH_DROP}
    out = tmp_path / "trials"
    assert main(["trials", "--task", "pick-place", "--objects", str(dominoes), "--episodes", "8", "--seed", "1000",
                 "--workers", "1", "--perception", "oracle", "--out", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["success"] >= 6, summary["failures"]


def test_thin_bars_dropped_in_a_stack_never_sink_into_the_table(tmp_path):
    """Eight 18 mm bars stacked for a drop (datagen's ``stack_drops``, up to 0.6 m high) fall and spin no faster
    than their stiffened contacts hold (``Workcell.cap_thin_speeds``): none ever sinks into the table."""
    trimesh.creation.box((0.1, 0.018, 0.018)).export(tmp_path / "bar.obj")
    assert main(["objects", "import", str(tmp_path / "bar.obj"), "--out", str(tmp_path / "set"), "--no-progress"]) == 0
    wcfg = with_objects(WorkcellConfig(), tmp_path / "set")
    cfg = SceneConfig(workcell=wcfg, min_spacing=0.03)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        types = choose_types(cfg, 8, rng)
        wc = Workcell(wcfg, [BlockInstance(t, (1.0, 0.0, 0.0, 1.0)) for t in types])
        for k, T in enumerate(stack_drops(drop_poses(cfg, types, rng), types), start=1):
            wc.set_block_pose(k, T)
        mujoco.mj_forward(wc.model, wc.data)
        lowest = [np.inf]
        wc.on_step = lambda w: lowest.__setitem__(0, min(lowest[0], w.block_poses()[:, 2, 3].min()))
        settle(wc, cfg)
        assert lowest[0] > 0.0, (seed, lowest[0])  # a bar's centre lies 9 mm or more above the table
        assert wc.data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number == 0, seed


def test_a_sphere_turns_about_three_orthogonal_axes_and_is_planned_quickly(tmp_path):
    trimesh.creation.icosphere(3, radius=0.03).export(tmp_path / "ball.stl")
    assert main(["objects", "import", str(tmp_path / "ball.stl"), "--out", str(tmp_path / "set"), "--no-progress"]) == 0
    ball = load_catalog(tmp_path / "set")["ball"]
    axes = np.array([a for a, _ in ball.symmetries_continuous])
    assert axes.shape == (3, 3) and np.allclose(axes @ axes.T, np.eye(3), atol=1e-6)
    assert len(symmetry_transforms(ball)) == 27  # 3 turns about each axis, not 36 ** 3
    t0 = time.perf_counter()
    on_table = make_T(np.eye(3), (0.45, 0.0, 0.03))
    grasps = plan_grasps(ball, on_table, np.zeros((0, 3)), GraspConfig(), yaw_now=0.0)
    assert grasps and time.perf_counter() - t0 < 10.0
    assert abs(grasps[0].width - 0.06) < 0.003
