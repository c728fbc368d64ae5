"""The workcell on the real simulator and renderer: settling, geometry of labels, determinism, arm control."""

from __future__ import annotations

import dataclasses

import cv2
import mujoco
import numpy as np
import pytest
import trimesh

from posegrasp.catalog import load_catalog
from posegrasp.geometry import invert, rotation_angle, transform_points
from posegrasp.gl import pyrender_renderer
from posegrasp.grasping.report.figures import silhouette
from posegrasp.sim.camera import CameraRenderer, Frame
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.scene import SceneConfig, make_scene
from posegrasp.sim.robot import ROBOT_MOUNT, robot_mjcf
from posegrasp.sim.suction import WELD_SOLIMP, WELD_SOLREF, weld_name
from posegrasp.sim.workcell import HAND_CAMERA, OVERVIEW_CAMERA, BlockInstance, Workcell, _add_block, build_mjcf


def capture_at_look(seed: int, n_blocks: int = 5, width: int = 640, height: int = 480) -> tuple[Frame, object]:
    cfg = WorkcellConfig()
    scene = make_scene(seed, n_blocks, SceneConfig(workcell=cfg))
    wc = scene.workcell
    assert wc.drive_arm(wc.look_q)
    c = cfg.hand_camera
    r = CameraRenderer(wc, HAND_CAMERA, dataclasses.replace(c, width=width, height=height))
    frame = r.capture()
    r.close()
    return frame, scene


@pytest.fixture(scope="module")
def look_frame():
    return capture_at_look(seed=3)


def max_penetration(wc) -> float:
    """Deepest contact penetration (m, >= 0) involving any block."""
    m, d = wc.model, wc.data
    blocks = set(wc.block_body.tolist())
    worst = 0.0
    for c in d.contact[: d.ncon]:
        if m.geom_bodyid[c.geom1] in blocks or m.geom_bodyid[c.geom2] in blocks:
            worst = max(worst, -float(c.dist))
    return worst


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_scene_settles_inside_pick_area(seed):
    scene = make_scene(seed, 5)
    assert scene.in_pick_area().all()
    speeds = scene.workcell.block_speeds()
    assert np.all(speeds[:, 0] < 0.005) and np.all(speeds[:, 1] < 0.15)
    assert max_penetration(scene.workcell) < 1e-3
    z = scene.workcell.block_poses()[:, 2, 3]
    assert np.all(z > 0.0) and np.all(z < 0.08)


def backproject(depth: np.ndarray, K: np.ndarray, mask: np.ndarray) -> np.ndarray:
    v, u = np.nonzero(mask & (depth > 0))
    z = depth[v, u].astype(np.float64)
    return np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)


def test_depth_lies_on_model_surface(look_frame):
    frame, scene = look_frame
    checked = 0
    for k, inst in enumerate(scene.blocks, start=1):
        pts_cam = backproject(frame.depth, frame.K, frame.mask == k)
        if len(pts_cam) < 50:
            continue
        T_obj_cam = invert(frame.T_cam_obj[k - 1])
        pts_obj = pts_cam @ T_obj_cam[:3, :3].T + T_obj_cam[:3, 3]
        mesh = trimesh.Trimesh(inst.block.vertices, inst.block.faces, process=False)
        _, dist, _ = trimesh.proximity.closest_point(mesh, pts_obj[:: max(1, len(pts_obj) // 1500)])
        assert np.median(dist) < 1e-3, (inst.block.name, np.median(dist))
        assert np.percentile(dist, 95) < 3e-3, (inst.block.name, np.percentile(dist, 95))
        checked += 1
    assert checked >= 3


def pyrender_silhouette(block, T_cam_obj: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool: ``block``'s mesh at ``T_cam_obj`` (OpenCV camera) rendered alone by pyrender."""
    import pyrender

    r = pyrender_renderer(width, height)
    # pyrender's principal point is in pixel-edge coordinates; OpenCV's K uses pixel centres.
    cam = pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, znear=0.02, zfar=5.0)
    sc = pyrender.Scene()
    sc.add(pyrender.Mesh.from_trimesh(trimesh.Trimesh(block.vertices, block.faces, process=False), smooth=False),
           pose=T_cam_obj)
    sc.add(cam, pose=np.diag([1.0, -1.0, -1.0, 1.0]))  # OpenCV camera -> OpenGL camera
    return r.render(sc, flags=pyrender.RenderFlags.DEPTH_ONLY) > 0


def pyrender_silhouettes(frame: Frame, scene, width: int, height: int) -> list[np.ndarray]:
    """Each block rendered alone by pyrender from its PLY-equivalent mesh at the ground-truth pose."""
    return [pyrender_silhouette(inst.block, frame.T_cam_obj[k], frame.K, width, height)
            for k, inst in enumerate(scene.blocks)]


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_masks_agree_with_pyrender(look_frame):
    frame, scene = look_frame
    h, w = frame.mask.shape
    sil = pyrender_silhouettes(frame, scene, w, h)
    checked = 0
    for k, s in enumerate(sil, start=1):
        others = np.any([o for j, o in enumerate(sil, start=1) if j != k], axis=0)
        if not s.any() or (s & others).any() or s[0].any() or s[-1].any() or s[:, 0].any() or s[:, -1].any():
            continue  # occluded by another block or cut by the image border
        assert iou(frame.mask == k, s) >= 0.97, (scene.blocks[k - 1].block.name, iou(frame.mask == k, s))
        checked += 1
    assert checked >= 3


def test_report_silhouettes_agree_with_pyrender(look_frame):
    """The report's filled-triangle silhouettes hold pyrender's pixels and at most the ring of pixels around them
    (a triangle's border pixels are filled), for every block in view; nothing behind the camera is drawn."""
    frame, scene = look_frame
    h, w = frame.mask.shape
    checked = 0
    for k, inst in enumerate(scene.blocks):
        ref = pyrender_silhouette(inst.block, frame.T_cam_obj[k], frame.K, w, h)
        if ref.any():
            s = silhouette(inst.block, frame.T_cam_obj[k], frame.K, w, h)
            ring = cv2.dilate(ref.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            assert max((ref & ~s).sum(), (s & ~ring).sum()) <= 0.002 * ref.sum(), inst.block.name
            checked += 1
    assert checked >= 3
    behind = frame.T_cam_obj[0].copy()
    behind[2, 3] = -behind[2, 3]  # mirrored behind the camera: nothing drawn
    assert not silhouette(scene.blocks[0].block, behind, frame.K, w, h).any()


def mujoco_mask(cam: CameraRenderer) -> np.ndarray:
    """``cam``'s instance mask from its renderer's own segmentation: ``mujoco.Renderer``'s (object id, type) pairs."""
    cam.renderer.enable_segmentation_rendering()
    cam._update()
    seg = cam.renderer.render()
    cam.renderer.disable_segmentation_rendering()
    return cam.wc.geom_instance[np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)]


@pytest.mark.slow
def test_shared_gl_context_renders_like_an_own_one():
    """Renderers sharing the process's GL context, two drawing in turns, across scenes, give the images of a
    ``mujoco.Renderer`` with a GL context of its own, and the masks its own segmentation maps to; a single-sampled
    renderer (``antialias=False``) the same masks, and colour without anti-aliasing."""
    for seed in (1, 2):
        wc = make_scene(seed, 3).workcell
        assert wc.drive_arm(wc.look_q, tol=0.01)
        c, o, r = wc.cfg.hand_camera, wc.cfg.overview_camera, wc.cfg.render
        own = CameraRenderer(wc, HAND_CAMERA, c, r)
        own.renderer.close()
        own.renderer = mujoco.Renderer(wc.model, c.height, c.width)
        own.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = r.shadows
        own.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = r.reflections
        want = [own.rgb(), own.depth(), mujoco_mask(own)]
        hand = CameraRenderer(wc, HAND_CAMERA, c, r)
        over = CameraRenderer(wc, OVERVIEW_CAMERA, o, r)
        overview = over.rgb()
        got = []
        for kind in ("rgb", "depth", "mask"):
            got.append(getattr(hand, kind)())
            np.testing.assert_array_equal(over.rgb(), overview)  # draws between the hand camera's passes
        for name, a, b in zip(("rgb", "depth", "mask"), want, got):
            np.testing.assert_array_equal(a, b, err_msg=name)
        assert (got[2] > 0).sum() > 1000 and overview.shape == (o.height, o.width, 3)
        labels = CameraRenderer(wc, HAND_CAMERA, c, r, antialias=False)
        np.testing.assert_array_equal(labels.mask(), got[2])
        assert not np.array_equal(labels.rgb(), got[0])
        for x in (own, hand, over, labels):
            x.close()


def test_same_seed_same_scene_different_seed_differs():
    a, _ = capture_at_look(seed=7, n_blocks=3, width=160, height=120)
    b, _ = capture_at_look(seed=7, n_blocks=3, width=160, height=120)
    c, _ = capture_at_look(seed=8, n_blocks=3, width=160, height=120)
    for name in ("rgb", "depth", "mask", "T_cam_obj", "T_world_cam"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert not np.array_equal(a.rgb, c.rgb)
    assert not np.allclose(a.T_cam_obj, c.T_cam_obj)


def test_arm_reaches_look_pose_with_actuators(look_frame):
    _, scene = look_frame
    wc = scene.workcell
    target = wc.look_camera_pose()
    reached = wc.camera_pose()
    assert np.linalg.norm(reached[:3, 3] - target[:3, 3]) < 0.01
    assert np.rad2deg(rotation_angle(reached[:3, :3], target[:3, :3])) < 2.0
    assert np.allclose(wc.data.ctrl[wc.arm_act], wc.data.ctrl[wc.arm_act])  # driven through actuators
    assert wc.data.time > 0.5


def test_the_arm_is_set_at_a_view_unless_it_would_touch_the_scene():
    """``place_arm``: the arm set at the look pose's joint angles exactly, no time simulated; joint angles that put
    the hand camera into a block are refused and leave the arm where it was."""
    wc = make_scene(3, 5).workcell
    t, q0 = wc.data.time, wc.arm_q
    assert wc.place_arm(wc.look_q)
    assert np.array_equal(wc.arm_q, wc.look_q) and wc.data.time == t
    assert np.linalg.norm(wc.camera_pose()[:3, 3] - wc.look_camera_pose()[:3, 3]) < 1e-3
    into = wc.look_camera_pose()
    into[:3, 3] = wc.block_poses()[0][:3, 3]
    q, dp, _ = wc.solve_camera_ik(into)
    assert dp < 0.01
    assert not wc.place_arm(q)
    assert np.array_equal(wc.arm_q, wc.look_q) and not np.array_equal(wc.arm_q, q0)


def test_hand_camera_sees_whole_pick_area(look_frame):
    frame, scene = look_frame
    a = scene.cfg.workcell.pick_area
    corners = np.array([[a.center[0] + sx * a.half_size[0], a.center[1] + sy * a.half_size[1], 0.0, 1.0]
                        for sx in (-1, 1) for sy in (-1, 1)])
    p = (invert(frame.T_world_cam) @ corners.T)[:3]
    uv = (frame.K @ p)[:2] / p[2]
    h, w = frame.mask.shape
    assert np.all(p[2] > 0) and np.all((uv[0] >= 0) & (uv[0] < w) & (uv[1] >= 0) & (uv[1] < h))


def test_camera_mount_matches_config():
    from posegrasp.sim.camera import rpy_deg_to_R

    cfg = WorkcellConfig()
    T = Workcell(cfg).T_gripper_cam()
    np.testing.assert_allclose(T[:3, 3], cfg.hand_camera.mount_pos, atol=1e-6)
    np.testing.assert_allclose(T[:3, :3], rpy_deg_to_R(cfg.hand_camera.mount_rpy_deg), atol=1e-6)


def test_shipped_toml_equals_defaults():
    from posegrasp.sim.config import load_workcell_config

    assert load_workcell_config() == WorkcellConfig()


def test_unplaced_blocks_touch_nothing():
    """Blocks wait apart, off the table, until placed: compiled all at the origin, 8 large hulls overlapping each
    other and the arm overflowed MuJoCo's constraint memory at the first forward pass (a datagen scene did)."""
    from posegrasp.catalog import load_catalog
    from posegrasp.sim.workcell import BlockInstance, Workcell

    cat = load_catalog()
    big = max(cat.values(), key=lambda b: b.diameter)
    wc = Workcell(WorkcellConfig(), [BlockInstance(big, (0.8, 0.2, 0.2, 1.0))] * 8)
    block_geoms = set(np.flatnonzero(np.isin(wc.model.geom_bodyid, wc.block_body)))
    touching = {int(g) for c in wc.data.contact[:wc.data.ncon] for g in (c.geom1, c.geom2)}
    assert not touching & block_geoms
    assert np.all(wc.block_poses()[:, 0, 3] == 0.0) and len({float(y) for y in wc.block_poses()[:, 1, 3]}) == 8


def test_the_hand_points_lie_on_the_hand_and_move_with_it():
    """``robot_surface.hand_points``: in the gripper frame the same points wherever the arm is (the fingers still),
    around the pinch point (the open fingers either side of it along the squeeze axis, nothing beyond the hand's
    25 cm); in the world they moved with the arm."""
    from posegrasp.sim.robot_surface import hand_points

    wc = Workcell(WorkcellConfig(hand="2-finger"))
    before, T_before = hand_points(wc), wc.gripper_pose()
    assert wc.place_arm(wc.look_q)
    after, T_after = hand_points(wc), wc.gripper_pose()
    local = [transform_points(np.linalg.inv(T), p) for T, p in ((T_before, before), (T_after, after))]
    assert np.allclose(local[0], local[1], atol=1e-6) and not np.allclose(before, after, atol=1e-3)
    assert local[0][:, 0].min() < -0.03 and local[0][:, 0].max() > 0.03  # the fingers either side of the pinch
    assert np.linalg.norm(local[0], axis=1).max() < 0.25


@pytest.mark.parametrize("hand", ["3-finger", "suction", "hybrid"])
def test_the_robot_attached_as_a_spec_is_the_model_of_one_mjcf(hand: str) -> None:
    """``compile_workcell`` attaches the once-parsed robot to each world: the compiled model must equal that of one
    dm-control MJCF holding the world, the robot, the parts and the cup's welds (every array but the names), but for
    the native convex collision the arm's model turns off."""
    cfg = WorkcellConfig(hand=hand)
    parts = load_catalog()
    blocks = [BlockInstance(parts[n], (0.2, 0.4, 0.6, 1.0)) for n in ("cube", "arch", "triangular_prism")]
    wc = Workcell(cfg, blocks)
    root = build_mjcf(cfg)
    root.find("body", ROBOT_MOUNT).remove()
    robot, cup = robot_mjcf(cfg)
    root.attach(robot)
    for k, inst in enumerate(blocks, start=1):
        _add_block(root, k, inst, cfg.timestep)
        if cup is not None:
            root.equality.add("weld", name=weld_name(k), body1=cup, body2=f"block_{k}", active="false",
                              solref=WELD_SOLREF, solimp=WELD_SOLIMP)
    one = mujoco.MjModel.from_xml_string(root.to_xml_string(), root.get_assets())
    arrays = [a for a in dir(one) if isinstance(getattr(one, a), np.ndarray) and not a.startswith("_")
              and "name" not in a and "path" not in a]
    assert [a for a in arrays if not np.array_equal(getattr(one, a), getattr(wc.model, a), equal_nan=True)] == []
    native = int(mujoco.mjtDisableBit.mjDSBL_NATIVECCD)
    assert one.opt.disableflags == wc.model.opt.disableflags | native and one.opt.timestep == wc.model.opt.timestep
    assert not wc.model.opt.disableflags & native


def test_ik_velocity_is_minks():
    """``sim.ik.velocity`` (DAQP called directly) gives ``mink.solve_ik``'s velocity bit for bit, joint limits
    active or not."""
    import mink

    from posegrasp.sim.ik import velocity

    wc = make_scene(0, 3).workcell
    ik, g = wc.ik, np.random.default_rng(0)
    site = f"jaco_arm/jaco_hand/{HAND_CAMERA}"
    for _ in range(40):
        q = ik.model.qpos0.copy()
        q[ik.arm_qadr] = wc.arm_q + g.normal(0, 0.6, 6)
        ik.configuration.update(q)
        T = ik.configuration.get_transform_frame_to_world(site, "site").as_matrix()
        T[:3, 3] += g.normal(0, 0.1, 3)
        task = mink.FrameTask(site, "site", position_cost=1.0, orientation_cost=0.5, lm_damping=1e-3)
        task.set_target(mink.SE3.from_matrix(T))
        posture = mink.PostureTask(ik.model, cost=1e-3)
        posture.set_target(q)
        want = mink.solve_ik(ik.configuration, [task, posture], 0.05, "daqp", damping=1e-4, limits=ik.limits)
        assert velocity(ik.configuration, [task, posture], 0.05, 1e-4, ik.limits).tobytes() == want.tobytes()
