"""The depth fit (``perception.depth_fit``): ICP from rotation hypotheses recovers a block turned onto a
near-symmetry."""

import dataclasses
import itertools

import numpy as np

import pytest
import torch
from scipy.spatial import cKDTree

from posegrasp.perception.runtime import torch_threads
from posegrasp.perception.depth_fit import (FitConfig, NearestGrid, ObjectModel, DepthFitConfig, ScoreConfig, SearchConfig,
                                        StartConfig, TurnConfig, cube_rotations, distinct_rotations, fit_pose,
                                        fit_poses)
from posegrasp.perception.metrics import rotation_error_sym_deg
from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.geometry import axis_angle_R, make_T


def test_cube_rotations_are_the_24_axis_maps():
    Q = cube_rotations()
    assert Q.shape == (24, 3, 3) and np.allclose(np.linalg.det(Q), 1.0)
    assert len({tuple(np.round(q).astype(int).ravel()) for q in Q}) == 24


def test_distinct_rotations_drop_hypotheses_equal_under_symmetry():
    Q = cube_rotations()
    half_turns = [make_T(axis_angle_R(np.eye(3)[i], np.pi), np.zeros(3)) for i in range(3)]
    assert len(distinct_rotations(Q, [], [])) == 24
    assert len(distinct_rotations(Q, half_turns, [])) == 6  # a box: 24 / 4
    assert len(distinct_rotations(Q, list(Q[1:]), [])) == 1  # a cube (rotation parts given as 3x3)
    cyl = distinct_rotations(Q, half_turns[:1], [np.array([0.0, 0.0, 1.0])])
    assert len(cyl) == 3  # axis along x, y or z of the estimate
    assert np.allclose(cyl[0], np.eye(3))  # the estimate itself stays first


@pytest.mark.parametrize("build, message", [
    (lambda: FitConfig(polish=-1), r"FitConfig\.polish = -1 is out of range: use 0 to"),
    (lambda: FitConfig(max_points=2), r"FitConfig\.max_points = 2 is out of range: use 3 to"),
    (lambda: ScoreConfig(truncation=0.0), r"ScoreConfig\.truncation = 0\.0 is out of range"),
    (lambda: ScoreConfig(float_weight=-1.0), r"ScoreConfig\.float_weight = -1\.0 is out of range"),
    (lambda: TurnConfig(seeds=0), r"TurnConfig\.seeds = 0 is out of range: use 1 to"),
    (lambda: SearchConfig(pattern_fits=0), r"SearchConfig\.pattern_fits = 0 is out of range: use 1 to"),
    (lambda: DepthFitConfig(score=ScoreConfig(rank_points=2000)),
     r"score\.rank_points = 2000 exceeds fit\.model_points = 1500"),
    (lambda: StartConfig(hypotheses="sphere"), r"StartConfig\.hypotheses = 'sphere': use 'cube' or 'identity'")])
def test_depth_fit_config_names_the_bad_value(build, message):
    """A bad value is refused when the settings are built, in one line naming the setting and the value."""
    with pytest.raises(ValueError, match=message):
        build()


def test_depth_fit_config_loads_its_stages_from_a_table():
    """The settings nest by stage, as a TOML table would give them; a flat key is refused with the valid ones named."""
    from posegrasp.config import from_dict
    from posegrasp.errors import UserError

    cfg = from_dict(DepthFitConfig, {"fit": {"polish": 2}, "search": {"pattern_rounds": 0}})
    assert cfg == DepthFitConfig(fit=FitConfig(polish=2), search=SearchConfig(pattern_rounds=0))
    with pytest.raises(UserError, match=r"unknown key\(s\) \['polish'\]; valid keys are \['fit', 'score'"):
        from_dict(DepthFitConfig, {"polish": 2})
    with pytest.raises(UserError, match=r"cfg\.fit\.polish = -1 is out of range"):
        from_dict(DepthFitConfig, {"fit": {"polish": -1}}, where="cfg")
    with pytest.raises(UserError, match=r"^cfg: score\.rank_points = 2000 exceeds fit\.model_points = 1000"):
        from_dict(DepthFitConfig, {"fit": {"model_points": 1000}, "score": {"rank_points": 2000}}, where="cfg")


def test_nearest_grid_matches_within_half_a_cell_diagonal():
    """The grid's point is at most a cell diagonal farther than the exact nearest model point (the query and the
    exact nearest point each lie within half a diagonal of the cell centre); most matches are exact."""
    rng = np.random.default_rng(0)
    model = rng.uniform(-1, 1, (500, 3)) * [0.03, 0.015, 0.01]
    grid = NearestGrid(model, cell=0.002, margin=0.01)
    q = rng.uniform(-0.06, 0.06, (4000, 3))  # inside and outside the grid (margin 1 cm)
    d_grid = np.linalg.norm(q - model[grid(torch.from_numpy(q).float()).numpy()], axis=1)
    d_true = cKDTree(model).query(q)[0]
    inside = np.all(np.abs(q) < np.abs(model).max(axis=0) + 0.01, axis=1)
    assert np.all(d_grid[inside] - d_true[inside] <= 0.002 * np.sqrt(3) + 1e-6)
    assert np.mean(np.isclose(d_grid, d_true)) > 0.6  # most are exact
    with pytest.raises(ValueError, match="cell > 0"):
        NearestGrid(model, cell=0.0)
    with pytest.raises(ValueError, match="truncation"):  # a field that stops short of the score's truncation
        fit_poses([np.eye(4)], [ObjectModel.of_points(model, grid=grid)], [model[:50]], np.zeros((8, 8)), np.eye(3),
                     DepthFitConfig(score=ScoreConfig(truncation=0.02)))


def test_stacked_grids_are_kept_per_list_of_grids():
    """``Grids.of`` gives the same stack for the same grids in the same order, a new one for another list, and builds
    a list's stack anew once ``KEPT`` other lists came after it; a kept stack looks up what a new one does."""
    from posegrasp.perception.depth_fit import grids as grids_mod
    from posegrasp.perception.depth_fit.grids import Grids

    rng = np.random.default_rng(1)
    gs = [NearestGrid(rng.uniform(-0.02, 0.02, (100, 3)), margin=0.01) for _ in range(grids_mod.KEPT + 2)]
    a = Grids.of(gs[:2], 100)
    assert Grids.of(gs[:2], 100) is a and Grids.of(gs[1::-1], 100) is not a and Grids.of(gs[:2], 120) is not a
    for g in gs[2:]:
        Grids.of([g], 100)
    b = Grids.of(gs[:2], 100)
    assert b is not a
    q, obj = torch.from_numpy(rng.uniform(-0.03, 0.03, (2, 50, 3))).float(), torch.tensor([0, 1])
    assert torch.equal(a(q, obj), b(q, obj)) and torch.equal(a(q, obj), Grids(gs[:2], 100)(q, obj))


def _kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weighted least-squares R, t of dst ~ R src + t (N, 3 each), by the SVD, in float64."""
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    U, _, Vt = np.linalg.svd((src - cs).T @ (w[:, None] * (dst - cd)))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs


def _two_objects(rng: np.random.Generator):
    """A ``FitContext`` of two models (500 and 300 points, object frame) seen as noisy points (200 and 120, camera
    frame) at random poses, the second's points all on one plane of its frame (a face seen alone: C of rank 2);
    with each observed point's model row and the true poses."""
    from posegrasp.perception.depth_fit.context import FitContext

    models = [rng.uniform(-1, 1, (500, 3)) * [0.03, 0.015, 0.01], rng.uniform(-1, 1, (300, 3)) * 0.02]
    models[1][:, 2] = 0.02
    rows = [rng.choice(500, 200, replace=False), rng.choice(300, 120, replace=False)]
    poses = [make_T(axis_angle_R(v / np.linalg.norm(v), a), [0.02 * i, -0.01, 0.4 + 0.05 * i])
             for i, (v, a) in enumerate(zip(rng.normal(size=(2, 3)), rng.uniform(0.5, 2.5, 2)))]
    observed = [m[r] @ T[:3, :3].T + T[:3, 3] + rng.normal(scale=0.001, size=(len(r), 3))
                for m, r, T in zip(models, rows, poses)]
    frame = FitContext.of([ObjectModel.of_points(m) for m in models], observed, np.zeros((8, 8)), np.eye(3), None)
    return frame, models, observed, rows, poses


def test_icp_steps_are_the_weighted_least_squares_fits():
    """``icp.steps``: each step is the weighted Kabsch fit (the SVD's, float64, to float32's precision) of the observed
    points to their matched model points, the grid's or (``exact``) the nearest (a k-d tree's), for 1 and 5 steps, of
    a full-rank and of a rank-2 cross-covariance alike, rows of one object repeated."""
    from posegrasp.perception.depth_fit import icp

    rng = np.random.default_rng(2)
    frame, models, observed, rows, poses = _two_objects(rng)
    obj = torch.tensor([0, 1, 1])
    off = [make_T(axis_angle_R(np.array([1.0, 0.0, 0.0]), np.radians(4)), [0.005, 0.0, 0.0]) @ poses[o]
           for o in obj.tolist()]
    R0 = torch.tensor(np.stack([T[:3, :3] for T in off]), dtype=torch.float32)
    t0 = torch.tensor(np.stack([T[:3, 3] for T in off]), dtype=torch.float32)
    no = torch.zeros(3, dtype=torch.bool)
    trees = [cKDTree(m) for m in models]
    for exact, n in itertools.product((False, True), (1, 5)):
        R, t = icp.steps(frame, R0, t0, obj, no, torch.zeros(3), n, exact=exact)
        R_ref, t_ref = R0.double().numpy(), t0.double().numpy()
        for _ in range(n):
            for h, o in enumerate(obj.tolist()):
                local = (observed[o] - t_ref[h]) @ R_ref[h]  # object frame
                if exact:
                    match = trees[o].query(local)[1]
                else:
                    x = torch.from_numpy(local).float()[None]
                    match = (frame.grids(x, obj[h:h + 1])[0].long() - o * frame.models.shape[1]).numpy()
                R_ref[h], t_ref[h] = _kabsch(models[o][match], observed[o], np.ones(len(rows[o])))
        np.testing.assert_allclose(R.numpy(), R_ref, atol=2e-5)
        np.testing.assert_allclose(t.numpy(), t_ref, atol=2e-5)


@pytest.mark.slow
def test_icp_leaves_a_near_symmetric_wrong_rotation(tiny_bop):
    """The tiny set's 60 x 30 x 20 mm box (obj 3), its estimate turned 90 deg about its z axis (not one of
    its symmetries, but ADD-S barely sees it) and shifted 4 mm: the hypotheses find the true pose back."""
    info = bop.load_models_info(tiny_bop)[3]
    model = bop_models.sample_model_points(bop_models.load_model(tiny_bop, 3), 500, seed=3)
    hyps = distinct_rotations(cube_rotations(), info.symmetries_discrete, [])
    assert len(hyps) == 6
    fixed, stuck = 0, 0
    recs = list(bop.iter_scene_images(tiny_bop, "train"))
    for rec in recs:
        g = next(g for g in rec.instances if g.obj_id == 3)
        depth, K = rec.load_depth(), rec.camera.K
        m = rec.load_mask(g.gt_index) & (depth > 0)
        vs, us = np.nonzero(m)
        z = depth[vs, us].astype(np.float64)
        obs = np.stack([(us - K[0, 2]) * z / K[0, 0], (vs - K[1, 2]) * z / K[1, 1], z], axis=1)
        T_est = g.T_cam_obj @ make_T(axis_angle_R(np.array([0.0, 0.0, 1.0]), np.pi / 2), np.array([0.004, 0.0, 0.0]))

        def err(T):
            return rotation_error_sym_deg(T[:3, :3], g.T_cam_obj[:3, :3], info.symmetries_discrete)

        for Q in (None, hyps):  # all 24 hypotheses, and the 6 that differ under the box's symmetries
            T, _ = fit_pose(T_est, ObjectModel.of_points(model, hypotheses=Q), obs[::max(1, len(obs) // 300)],
                               depth, K)
            fixed += err(T) < 10.0 and np.linalg.norm(T[:3, 3] - g.T_cam_obj[:3, 3]) < 0.005
        plain = DepthFitConfig(starts=StartConfig(hypotheses="identity"), turns=TurnConfig(step_deg=0.0))
        T1, _ = fit_pose(T_est, ObjectModel.of_points(model, plain), obs[::max(1, len(obs) // 300)], depth, K, plain)
        stuck += err(T1) > 45.0
    # measured: 7 of 8 recovered with the 24 hypotheses, 7 of 8 with the 6; plain ICP stays turned in 8 of 8
    assert fixed >= 2 * 0.75 * len(recs) and stuck >= 0.75 * len(recs)


@pytest.mark.slow
def test_objects_fitted_together_as_each_alone(tiny_bop):
    """``fit_poses`` batches the objects of a frame (models and point sets of different sizes, padded): each result
    is ``fit_pose``'s for that object alone, with and without the supporting plane, and the very same with the batch's
    rows shared out over a torch thread per object."""
    rec = next(iter(bop.iter_scene_images(tiny_bop, "train")))
    depth, K = rec.load_depth(), rec.camera.K
    infos = bop.load_models_info(tiny_bop)
    args = []
    for k, g in enumerate(rec.instances):
        model = bop_models.sample_model_points(bop_models.load_model(tiny_bop, g.obj_id), 300 + 100 * k, seed=k)
        vs, us = np.nonzero(rec.load_mask(g.gt_index) & (depth > 0))
        z = depth[vs, us].astype(np.float64)
        obs = np.stack([(us - K[0, 2]) * z / K[0, 0], (vs - K[1, 2]) * z / K[1, 1], z], axis=1)[::3 + k]
        T_est = g.T_cam_obj @ make_T(axis_angle_R(np.array([0.0, 0.0, 1.0]), 0.3), np.array([0.004, 0.0, 0.0]))
        Q = distinct_rotations(cube_rotations(), infos[g.obj_id].symmetries_discrete, [])
        args.append((T_est, ObjectModel.of_points(model, hypotheses=Q), obs))
    assert len(args) >= 2 and len({len(a[1].points) for a in args}) == len(args) and len({len(a[2]) for a in args}) > 1
    cfg = DepthFitConfig(fit=FitConfig(polish=2))
    for plane in (None, np.array([0.0, 0.0, -1.0, float(depth[depth > 0].max()) + 0.01])):
        with torch_threads(1):
            together = fit_poses(*[list(x) for x in zip(*args)], depth, K, cfg, plane)
        with torch_threads(len(args)):
            threaded = fit_poses(*[list(x) for x in zip(*args)], depth, K, cfg, plane)
        for (T, s), (T1, s1) in zip(together, threaded):
            np.testing.assert_array_equal(T, T1)
            assert s == s1
        for (T, s), (T_est, model, obs) in zip(together, args):
            T1, s1 = fit_pose(T_est, model, obs, depth, K, cfg, plane)
            np.testing.assert_allclose(T, T1, atol=1e-4)
            assert s == pytest.approx(s1, abs=1e-5)
    assert fit_poses([], [], [], depth, K) == []


def test_yaw_turns_repeat_no_turn_a_symmetry_gives():
    """Turns about the plane's normal: every step of 360 deg / (the symmetries about that axis); none for a continuous
    axis along it."""
    from posegrasp.perception.depth_fit.starts import yaw_turns

    up = np.array([0.0, 0.0, 1.0])
    quarter = np.stack([axis_angle_R(up, k * np.pi / 2) for k in (1, 2, 3)])
    none, axes = np.zeros((0, 3, 3)), np.zeros((0, 3))
    np.testing.assert_allclose(np.degrees(yaw_turns(np.eye(3), up, 30.0, none, axes)), np.arange(12) * 30.0)
    np.testing.assert_allclose(np.degrees(yaw_turns(np.eye(3), up, 30.0, quarter, axes)), [0.0, 30.0, 60.0])
    np.testing.assert_allclose(np.degrees(yaw_turns(np.eye(3), up, 25.0, quarter[1:2], axes)),
                               np.arange(7) * 180.0 / 7)  # 180 deg in 7 even steps of ~25.7
    assert np.array_equal(yaw_turns(np.eye(3), up, 30.0, none, up[None]), [0.0])
    lying = axis_angle_R(np.array([1.0, 0.0, 0.0]), np.pi / 2)  # the quarter turns' axis now lies along -y
    assert len(yaw_turns(lying, up, 30.0, quarter, axes)) == 12


def _cube_on_table(yaw_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 25 mm cube on a table, its yaw ``yaw_deg``: ``_on_table``'s outputs."""
    import trimesh

    T_world_obj = make_T(axis_angle_R(np.array([0.0, 0.0, 1.0]), np.radians(yaw_deg)), np.array([0.0, 0.0, 0.0125]))
    return _on_table(trimesh.creation.box((0.025,) * 3), T_world_obj)


def _on_table(mesh, T_world_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A mesh (m) at T_world_obj on a table (z = 0), seen from 35 cm at 30 deg off vertical (pyrender, 320 x 240):
    T_cam_obj, the object's camera-frame points, the depth image (m), K and the table plane (4,), camera frame."""
    import pyrender
    import trimesh

    from posegrasp.gl import pyrender_renderer

    K = np.array([[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]])
    tilt = axis_angle_R(np.array([1.0, 0.0, 0.0]), np.radians(180.0 - 30.0))  # camera z looks down, 30 deg off
    T_world_cam = make_T(tilt, tilt @ np.array([0.0, 0.0, -0.35]))
    T_cam_world = np.linalg.inv(T_world_cam)
    scene = pyrender.Scene()
    cam = pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], znear=0.05, zfar=2.0)
    scene.add(cam, pose=T_world_cam @ np.diag([1.0, -1.0, -1.0, 1.0]))
    scene.add(pyrender.Mesh.from_trimesh(trimesh.creation.box((0.4, 0.4, 0.01))), pose=make_T(np.eye(3), [0, 0, -0.005]))
    cube = scene.add(pyrender.Mesh.from_trimesh(mesh), pose=T_world_obj)
    renderer = pyrender_renderer(320, 240)  # the process's (deleting one would end every pyrender context's display)
    depth = renderer.render(scene, flags=pyrender.RenderFlags.DEPTH_ONLY)
    for node in scene.mesh_nodes:
        node.mesh.is_visible = node is cube
    alone = renderer.render(scene, flags=pyrender.RenderFlags.DEPTH_ONLY)
    vs, us = np.nonzero((alone > 0) & (np.abs(alone - depth) < 1e-4))
    z = depth[vs, us].astype(np.float64)
    obs = np.stack([(us - K[0, 2]) * z / K[0, 0], (vs - K[1, 2]) * z / K[1, 1], z], axis=1)
    n = T_cam_world[:3, 2]  # the table's normal and plane, camera frame
    plane = np.append(n, -n @ T_cam_world[:3, 3])
    return T_cam_world @ T_world_obj, obs, depth.astype(np.float32), K, plane


@pytest.mark.slow
def test_yaw_turns_find_a_cube_turned_on_the_table():
    """Seen from above, a cube's top face fits its points at almost any yaw, and free ICP keeps much of a yaw error
    it starts from (35 deg -> 16 deg measured); the turns about the table's normal find the true yaw back (2.3 deg),
    and so do, without them, the fits held level with the final yaw search (2.3 deg)."""
    import trimesh

    T_gt, obs, depth, K, plane = _cube_on_table(20.0)
    cube = trimesh.creation.box((0.025,) * 3)
    model = trimesh.sample.sample_surface_even(cube, 500, seed=0)[0]
    Q = cube_rotations()
    syms = (Q[1:], np.zeros((0, 3)))
    up = plane[:3]
    turn = make_T(axis_angle_R(up, np.radians(35.0)), np.zeros(3))
    T_est = turn @ T_gt
    T_est[:3, 3] = T_gt[:3, 3] + [0.003, 0.0, 0.0]

    def err(T):
        return rotation_error_sym_deg(T[:3, :3], T_gt[:3, :3], list(Q[1:]))

    cube_model = ObjectModel.of_points(model, hypotheses=distinct_rotations(Q, list(Q[1:]), []), symmetries=syms)
    T_turns, _ = fit_pose(T_est, cube_model, obs, depth, K, DepthFitConfig(), plane)
    plain = DepthFitConfig(starts=StartConfig(level_rests=False), turns=TurnConfig(step_deg=0.0),
                         search=SearchConfig(yaw_deg=0.0))
    T_plain, _ = fit_pose(T_est, cube_model, obs, depth, K, plain, plane)
    T_held, _ = fit_pose(T_est, cube_model, obs, depth, K, DepthFitConfig(turns=TurnConfig(step_deg=0.0)), plane)
    assert err(T_turns) < 5.0 and np.linalg.norm(T_turns[:3, 3] - T_gt[:3, 3]) < 0.002
    assert err(T_plain) > 10.0 and err(T_held) < 5.0


def test_up_face_names_the_object_axis_along_the_normal():
    from posegrasp.perception.depth_fit.starts import up_face

    up = np.array([0.0, 0.0, 1.0])
    R = torch.from_numpy(np.stack([np.eye(3), axis_angle_R(np.array([1.0, 0.0, 0.0]), np.pi),
                                   axis_angle_R(np.array([0.0, 1.0, 0.0]), np.pi / 2),
                                   axis_angle_R(np.array([1.0, 0.0, 0.0]), np.radians(100.0))]))
    # +z up; -z up (upside down); -x up (R^T up = (-1, 0, 0)); +y up, tilted 10 deg off it
    assert up_face(R, up).tolist() == [4, 5, 1, 2]


@pytest.mark.slow
def test_an_l_block_standing_as_an_inverted_v_is_found_from_its_rests():
    """An L-block standing on the ends of its two bars, corner up (its rest 45 deg from every object axis), estimated
    as an upright L turned 120 deg: levelled onto the nearest object axis, no resting start can reach that pose; the
    model's rests (``perception.depth_fit.rests``) give one that does."""
    from posegrasp.perception.depth_fit.rests import Rests

    mesh = bop_models.load_model("assets/blocks", 8)
    syms = bop.load_models_info("assets/blocks")[8].symmetry_rotations()
    rests = Rests.of_mesh(mesh, *syms)
    R_world_obj = axis_angle_R(np.array([0.0, 1.0, 0.0]), np.radians(135.0))  # object (-1, 0, -1) / sqrt 2 up
    lowest = (mesh.vertices @ R_world_obj.T)[:, 2].min()
    T_gt, obs, depth, K, plane = _on_table(mesh, make_T(R_world_obj, np.array([0.0, 0.0, -lowest])))
    T_est = make_T(axis_angle_R(plane[:3], np.radians(120.0)) @ T_gt[:3, :3] @ R_world_obj.T, T_gt[:3, 3] + 0.004)
    model = bop_models.sample_model_points(mesh, 500, seed=8)
    hyps = distinct_rotations(cube_rotations(), list(syms[0]), [])
    obs = obs[::max(1, len(obs) // 300)]

    def err(rests):
        T, _ = fit_pose(T_est, ObjectModel.of_points(model, hypotheses=hyps, symmetries=syms, rests=rests), obs,
                           depth, K, DepthFitConfig(), plane)
        return rotation_error_sym_deg(T[:3, :3], T_gt[:3, :3], list(syms[0]))

    assert err(rests) < 1.0  # 0.04 deg measured
    assert err(None) > 5.0  # 9.5 deg: a free fit, stuck tilted



def test_a_pose_floating_above_the_plane_costs_the_floating_term():
    """The score's floating term: a 2 cm cube and its observed points lifted 2, 8 and 30 mm above the table plane
    score the same fit, plus float_weight x (height - margin) / 1 cm, capped at float_weight."""
    from posegrasp.perception.depth_fit.context import FitContext
    from posegrasp.perception.depth_fit.score import score

    corners = np.array(list(itertools.product((-0.01, 0.01), repeat=3)))
    model = ObjectModel.of_points(np.concatenate([corners, np.random.default_rng(0).uniform(-0.01, 0.01, (300, 3))]))
    K = np.array([[500.0, 0, 32], [0, 500.0, 32], [0, 0, 1]])
    depth = np.zeros((64, 64))  # no depth seen: no free-space term
    plane = np.array([0.0, 0.0, -1.0, 0.5])  # the table 0.5 m from the camera, its normal towards the camera
    R, obj = torch.eye(3)[None], torch.zeros(1, dtype=torch.long)
    costs = []
    for lift in (0.002, 0.008, 0.030):
        t = torch.tensor([[0.0, 0.0, 0.49 - lift]])  # the cube's lowest face ``lift`` above the table
        frame = FitContext.of([model], [model.points + t.numpy()], depth, K, plane)
        on, off = (score(frame, cfg, R, t, obj, fine=True) for cfg in (ScoreConfig(), ScoreConfig(float_weight=0.0)))
        costs.append(float(on - off))
    np.testing.assert_allclose(costs, [0.0, 0.01 * 0.4, 0.01], atol=1e-6)


def _reference_score(frame, cfg: ScoreConfig, R: np.ndarray, t: np.ndarray, o: int, fine: bool) -> float:
    """The score (``perception.depth_fit.score``'s module doc) of one pose R (3, 3), t (3,) of object o, in float64
    numpy, distances from the torch lookups of the fields and the grids."""
    w = frame.weights[o].numpy().astype(np.float64)
    local = (frame.points[o].numpy() - t) @ R  # (N, 3), object frame
    x = torch.from_numpy(local).float()
    if fine:
        dist = frame.grids.fields(x.T[None], torch.tensor([o]))[0].numpy()
    else:
        dist = np.linalg.norm(local - frame.table[frame.grids(x[None], torch.tensor([o]))[0].long()].numpy(), axis=1)
    fit = (np.minimum(dist, cfg.truncation) * w).sum() / w.sum()
    k = frame.models.shape[1] if fine else min(cfg.rank_points, frame.models.shape[1])
    m = frame.models[o, :k].numpy()[frame.model_ok[o, :k].numpy()]
    c = m @ R.T + t  # camera frame
    K, depth = frame.K, frame.depth.numpy()
    z = np.maximum(c[:, 2], 1e-6)
    u, v = np.rint(c[:, 0] * K[0, 0] / z + K[0, 2]), np.rint(c[:, 1] * K[1, 1] / z + K[1, 2])
    seen = (u >= 0) & (u < depth.shape[1]) & (v >= 0) & (v < depth.shape[0])
    dz = depth[v[seen].astype(int), u[seen].astype(int)]
    viol = ((dz > 0) & (z[seen] < dz - cfg.violation_margin)).sum() / max(seen.sum(), 1)
    n, d = frame.plane[:3].numpy(), float(frame.plane[3])
    height = c @ n + d
    lowest = height.min()
    supports = frame.supports[o].numpy()
    lowest -= max([0.0] + [s for s in supports if s <= lowest + cfg.float_margin])
    floating = np.clip((lowest - cfg.float_margin) / 0.01, 0, 1)
    viol += (height < -cfg.violation_margin).mean()
    return fit + cfg.float_weight * floating + cfg.violation_weight * viol


def test_the_compiled_score_is_the_module_docs_score(tiny_bop):
    """``score`` (compiled) of 40 poses near the true ones of a real frame's objects, resting on each other and the
    table, with the frame's depth: the float64 reference's within float32 rounding, in the ranking (grid) and the
    fine (field) form; each term moves the score."""
    from posegrasp.perception.depth_fit.context import FitContext
    from posegrasp.perception.depth_fit.score import score

    rec = next(iter(bop.iter_scene_images(tiny_bop, "train")))
    depth, K = rec.load_depth(), rec.camera.K
    models, observed, truth = [], [], []
    for k, g in enumerate(rec.instances):
        points = bop_models.sample_model_points(bop_models.load_model(tiny_bop, g.obj_id), 600 + 300 * k, seed=k)
        models.append(ObjectModel.of_points(points))
        vs, us = np.nonzero(rec.load_mask(g.gt_index) & (depth > 0))
        z = depth[vs, us].astype(np.float64)
        observed.append(np.stack([(us - K[0, 2]) * z / K[0, 0], (vs - K[1, 2]) * z / K[1, 1], z], axis=1)[::2])
        truth.append(g.T_cam_obj)
    plane = np.array([0.0, 0.0, -1.0, float(depth[depth > 0].max()) + 0.002])
    rng = np.random.default_rng(5)
    obj = torch.from_numpy(rng.integers(0, len(models), 40))
    poses = [truth[o] @ make_T(axis_angle_R(rng.normal(size=3), rng.uniform(0, 0.3)), rng.normal(scale=s, size=3))
             for o, s in zip(obj.tolist(), [0.004] * 30 + [0.03] * 10)]  # the last 10 partly beyond their fields
    R = torch.tensor(np.stack([T[:3, :3] for T in poses]), dtype=torch.float32)
    t = torch.tensor(np.stack([T[:3, 3] for T in poses]), dtype=torch.float32)
    frame = FitContext.of(models, observed, depth, K, plane)
    supports = torch.zeros_like(frame.supports)  # every other pose's lowest point 2 mm under a support of its object
    for h, o in list(enumerate(obj.tolist()))[::2]:
        low = ((frame.models[o][frame.model_ok[o]] @ R[h].T + t[h]) @ frame.plane[:3] + frame.plane[3]).min()
        supports[o, 1 + h // 2 % (supports.shape[1] - 1)] = low + 0.002
    frame = dataclasses.replace(frame, supports=supports)
    for fine in (False, True):
        got = score(frame, ScoreConfig(), R, t, obj, fine=fine).numpy()
        want = [_reference_score(frame, ScoreConfig(), R[h].double().numpy(), t[h].double().numpy(), o, fine)
                for h, o in enumerate(obj.tolist())]
        np.testing.assert_allclose(got, want, atol=5e-5)  # a model point on a pixel's edge: 1 / k of the weight
        assert np.mean(np.abs(got - want) < 1e-6) > 0.9
    for term in ("violation_weight", "float_weight", "truncation"):
        cfg = dataclasses.replace(ScoreConfig(), **{term: 2 * getattr(ScoreConfig(), term)})
        assert not torch.equal(score(frame, cfg, R, t, obj, fine=True), score(frame, ScoreConfig(), R, t, obj, True))


def test_level_lays_the_nearest_axis_on_the_normal_by_the_least_turn():
    from posegrasp.perception.depth_fit.starts import level, resting

    rng = np.random.default_rng(0)
    n = torch.tensor([0.0, -0.6, -0.8], dtype=torch.float64)
    R = torch.from_numpy(np.stack([axis_angle_R(rng.normal(size=3), rng.uniform(0, np.pi)) for _ in range(50)]))
    L = level(R, n)
    a, b = R.transpose(1, 2) @ n, L.transpose(1, 2) @ n  # the normal in each object frame, before and after
    assert torch.allclose(b.abs().max(dim=1).values, torch.ones(50, dtype=torch.float64), atol=1e-9)
    assert torch.equal(a.abs().argmax(dim=1), b.abs().argmax(dim=1))  # the same face down
    turned = torch.arccos(((torch.einsum("hij,hij->h", R, L) - 1) / 2).clamp(-1, 1))
    assert torch.allclose(turned, torch.arccos(a.abs().max(dim=1).values), atol=1e-6)  # the least turn
    assert torch.allclose(level(L, n), L, atol=1e-9)
    # a 2 cm cube levelled and set on the plane n . x + 0.5 = 0: its lowest corner on it, its top face 2 cm above
    corners = torch.tensor(list(itertools.product((-0.01, 0.01), repeat=3)), dtype=torch.float64)[None]
    plane = torch.cat([n, torch.tensor([0.5], dtype=torch.float64)])
    t, _ = resting(L[:1], torch.zeros(1, 3, dtype=torch.float64), corners, torch.zeros(1, dtype=torch.long), plane)
    height = (corners[0] @ L[0].T + t[0]) @ n + 0.5
    assert float(height.min()) == pytest.approx(0.0, abs=1e-9) and float(height.max()) == pytest.approx(0.02, abs=1e-9)


def test_the_lowest_point_over_the_hull_is_the_lowest_model_point():
    """``starts.lowest`` over ``ObjectModel.hull`` gives every rotation the least height of all the model points (a
    few dozen vertices stand for 2000 points); points on a plane (no hull) give themselves."""
    from posegrasp.perception.depth_fit.starts import lowest

    rng = np.random.default_rng(1)
    points = rng.normal(size=(2000, 3)) * [0.03, 0.01, 0.02]
    model = ObjectModel.of_points(points)
    assert len(model.hull) < len(points) // 10
    R = torch.from_numpy(np.stack([axis_angle_R(rng.normal(size=3), rng.uniform(0, np.pi)) for _ in range(40)]))
    n = torch.tensor([0.0, -0.6, -0.8], dtype=torch.float64)
    every = (torch.from_numpy(points) @ (R.transpose(1, 2) @ n).T).min(dim=0).values
    hull = lowest(R, torch.from_numpy(model.hull)[None], torch.zeros(40, dtype=torch.long), n)
    assert torch.allclose(hull, every, rtol=0, atol=1e-12)
    flat = points * [1.0, 1.0, 0.0]
    assert np.array_equal(ObjectModel.of_points(flat).hull, flat)


def test_the_held_fit_turns_about_the_normal_and_shifts_to_the_exact_least_squares_pose():
    """``icp.steps`` with rows held: targets made by turning R0 m about the plane's normal n by 0.03 rad and shifting
    along the plane (a lattice of model points 1 cm apart, so that each point's nearest is its own) give back that
    turn and shift in one exact step (a free row the same), and each held row keeps its lowest model point's height
    ``low``; ``turns_about`` is Rodrigues' formula."""
    from posegrasp.perception.depth_fit import icp
    from posegrasp.perception.depth_fit.context import FitContext
    from posegrasp.perception.torch_geometry import turns_about

    n = np.array([0.0, -0.6, -0.8])
    src = np.stack(np.meshgrid(*[np.arange(k) * 0.01 for k in (4, 4, 3)], indexing="ij"), -1).reshape(-1, 3)
    R0 = np.stack([np.eye(3), axis_angle_R(np.array([1.0, 0.0, 0.0]), 0.3)])
    G, shift = axis_angle_R(n, 0.03), np.array([0.1, 0.2, 0.5])
    dst = [src @ (G @ R).T + shift for R in R0]
    plane = np.array([*n, 0.3], dtype=np.float32)  # the shift's height over it: n . shift + d
    low = torch.full((2,), -float(n @ shift + plane[3]))
    frame = FitContext.of([ObjectModel.of_points(src)] * 2, dst, np.zeros((8, 8)), np.eye(3), plane)
    f = lambda a: torch.from_numpy(a).float()  # noqa: E731
    t0 = f(np.tile(shift + 0.001 * np.cross(n, [1.0, 0.0, 0.0]), (2, 1)))  # 1 mm off along the plane
    for held in ([True, True], [False, True]):
        R, t = icp.steps(frame, f(R0), t0, torch.arange(2), torch.tensor(held), low, 1, exact=True)
        np.testing.assert_allclose(R.numpy(), G @ R0, atol=1e-5)
        np.testing.assert_allclose(t.numpy(), np.tile(shift, (2, 1)), atol=1e-5)
    turns = turns_about(f(n), torch.tensor([0.4, -1.0]))
    np.testing.assert_allclose(turns.numpy(), [axis_angle_R(n, 0.4), axis_angle_R(n, -1.0)], atol=1e-6)


def test_the_pattern_search_walks_a_pose_down_its_score_along_the_plane():
    """``pattern_search`` on a score that is the distance (m) to a target pose's position plus its turn about the
    normal (rad, scaled 10 cm per rad): from 3.4 mm and 3 deg off, in 2 rounds per scale, it ends within the last
    scale's steps (0.5 mm, 0.5 deg), keeps the pose's height over the plane and appends the moved pose."""
    from posegrasp.perception.depth_fit.score import Scored
    from posegrasp.perception.depth_fit.search import pattern_search

    n = torch.tensor([0.0, -0.6, -0.8], dtype=torch.float64)
    R_goal = torch.from_numpy(axis_angle_R(np.array([0.3, 0.2, 0.9]), 0.7))
    t_goal = torch.tensor([0.05, -0.02, 0.5], dtype=torch.float64)
    turn = torch.from_numpy(axis_angle_R(n.numpy(), np.radians(3.0)))
    e = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    along = e - (e @ n) * n  # a shift along the plane
    R0, t0 = turn @ R_goal, t_goal + 0.0034 * along / along.norm()

    def score_of(R, t, obj):
        cos = ((torch.einsum("hij,ij->h", R, R_goal) - 1) / 2).clamp(-1, 1)
        return (t - t_goal).norm(dim=1) + 0.1 * torch.arccos(cos)

    obj = torch.zeros(1, dtype=torch.long)
    start = Scored(R0[None], t0[None], obj, score_of(R0[None], t0[None], obj))
    out = pattern_search(start, n, torch.tensor([[[0.0, 0.0, 1.0]]], dtype=torch.float64),
                         SearchConfig(pattern_fits=1, pattern_rounds=2), score_of)
    R, t, s = out.R, out.t, out.score
    assert len(R) == 2 and torch.equal(R[0], R0) and float(s[1]) < float(s[0])
    assert float((t[1] - t_goal).norm()) < 0.0005 * np.sqrt(2) + 1e-9
    assert float(torch.arccos(((torch.trace(R[1].T @ R_goal) - 1) / 2).clamp(-1, 1))) < np.radians(0.5) + 1e-9
    assert float((t[1] - t0) @ n) == pytest.approx(0.0, abs=1e-12)  # moved along the plane only
