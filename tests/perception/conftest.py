"""A tiny BOP dataset rendered with pyrender for the perception tests (session-scoped)."""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from helpers import build_once  # noqa: E402
from bop_helpers import object_info_from_mesh, write_depth, write_mask, write_model_ply, write_models_info  # noqa: E402
from posegrasp import bop  # noqa: E402
from posegrasp.geometry import axis_angle_R, make_T  # noqa: E402
from posegrasp.gl import pyrender_renderer  # noqa: E402
from posegrasp.io import write_image  # noqa: E402

torch.set_num_threads(1 if os.environ.get("PYTEST_XDIST_WORKER") else 2)  # two workers: a core each

WIDTH, HEIGHT = 160, 120
K = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])
COLOURS = {1: (220, 60, 40), 2: (40, 160, 60), 3: (50, 80, 220)}


def _models():
    """obj 1: an L of two boxes (no symmetry); obj 2: a cylinder (continuous, z); obj 3: a box
    60 x 30 x 20 mm (discrete: 180 deg about x, y, z). Metres."""
    import trimesh

    a = trimesh.creation.box((0.06, 0.02, 0.02))
    b = trimesh.creation.box((0.02, 0.04, 0.02))
    b.apply_translation((-0.02, 0.03, 0.0))
    ell = trimesh.util.concatenate([a, b])
    ell.apply_translation(-ell.bounds.mean(axis=0))
    cyl = trimesh.creation.cylinder(radius=0.02, height=0.05, sections=24)
    box = trimesh.creation.box((0.06, 0.03, 0.02))
    flips = [make_T(axis_angle_R(np.eye(3)[i], np.pi), np.zeros(3)) for i in range(3)]
    return {
        1: (ell, [], []),
        2: (cyl, [], [(np.array([0.0, 0.0, 1.0]), np.zeros(3))]),
        3: (box, flips, []),
    }


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    from posegrasp.geometry import quat_to_R

    z = rng.uniform(0.3, 0.6)
    x = rng.uniform(-0.3, 0.3) * z
    y = rng.uniform(-0.22, 0.22) * z
    return make_T(quat_to_R(q), np.array([x, y, z]))


def make_tiny_bop(root: Path, n_train: int = 8, n_test: int = 3, seed: int = 0) -> Path:
    """Write a BOP dataset with 3 objects, splits train (scene 0) and test (scene 1)."""
    import pyrender

    models = _models()
    infos = {}
    for oid, (mesh, disc, cont) in models.items():
        mesh.visual.vertex_colors = np.array([*COLOURS[oid], 255], dtype=np.uint8)
        write_model_ply(root, oid, mesh)
        infos[oid] = object_info_from_mesh(oid, mesh, disc, cont)
    write_models_info(root, infos)
    bop.write_camera(root, bop.Camera(WIDTH, HEIGHT, K, depth_scale=0.1))

    renderer = pyrender_renderer(WIDTH, HEIGHT)  # kept: deleting one ends the EGL display MuJoCo renders on
    cam = pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], znear=0.05, zfar=3.0)
    cv_to_gl = np.diag([1.0, -1.0, -1.0, 1.0])
    meshes = {oid: pyrender.Mesh.from_trimesh(m, smooth=False) for oid, (m, _, _) in models.items()}
    rng = np.random.default_rng(seed)
    for split, scene_id, n in (("train", 0, n_train), ("test", 1, n_test)):
        sd = bop.scene_dir(root, split, scene_id)
        gts, cams, infos_gt = {}, {}, {}
        for im in range(n):
            poses = {oid: _random_pose(rng) for oid in models}
            scene = pyrender.Scene(ambient_light=np.full(3, 0.5), bg_color=[0.3, 0.3, 0.3, 1.0])
            scene.add(cam, pose=cv_to_gl)
            scene.add(pyrender.DirectionalLight(intensity=2.0), pose=cv_to_gl)
            nodes = {oid: scene.add(meshes[oid], pose=T) for oid, T in poses.items()}
            rgb, depth = renderer.render(scene)
            singles = {}
            for oid, node in nodes.items():
                for other in nodes.values():
                    other.mesh.is_visible = other is node
                singles[oid] = renderer.render(scene, flags=pyrender.RenderFlags.DEPTH_ONLY)
            for node in nodes.values():
                node.mesh.is_visible = True
            write_image(bop.image_path(sd, "rgb", im), rgb)
            write_depth(bop.image_path(sd, "depth", im), depth, depth_scale=0.1)
            gts[im], infos_gt[im] = [], []
            for gi, (oid, T) in enumerate(poses.items()):
                full = singles[oid] > 0
                visib = full & (np.abs(singles[oid] - depth) < 1e-3)
                write_mask(bop.mask_path(sd, im, gi, visible=False), full)
                write_mask(bop.mask_path(sd, im, gi, visible=True), visib)
                gts[im].append((oid, T))
                infos_gt[im].append(bop.gt_info_from_masks(full, visib, depth))
            cams[im] = bop.SceneCamera(K=K, depth_scale=0.1)
        bop.write_scene_gt(sd / "scene_gt.json", gts)
        bop.write_scene_camera(sd / "scene_camera.json", cams)
        bop.write_scene_gt_info(sd / "scene_gt_info.json", infos_gt)
    return root


@pytest.fixture(scope="session")
def tiny_bop(tmp_path_factory) -> Path:
    """Root of the tiny BOP dataset (3 objects, 8 train and 3 test images of 160 x 120 px)."""
    return build_once(tmp_path_factory, "tiny_bop", make_tiny_bop)


# --------------------------------------------------------------------------- a tiny trained run

def tiny_configs():
    """Small, fast training configs for the tiny dataset (CPU, a few seconds each)."""
    from posegrasp.perception.data import DataConfig
    from posegrasp.perception.pose_net import PoseNetConfig
    from posegrasp.perception.refiner import RefinerConfig
    from posegrasp.perception.seg_net import SegNetConfig
    from posegrasp.perception.train_pose import PoseTrainConfig
    from posegrasp.perception.train_refiner import RefinerTrainConfig
    from posegrasp.perception.train_seg import SegTrainConfig

    data = DataConfig(num_model_points=200, model_pool=1000)
    seg = SegTrainConfig(model=SegNetConfig(width=0.125, input_size=(96, 128)), data=data, batch_size=2, lr=0.05,
                         log_every=1, checkpoint_every=10, eval_every=0)
    pose = PoseTrainConfig(model=PoseNetConfig(num_points=128, crop_size=48, backbone_width=8, emb_dim=16,
                                               head_widths=(64, 32, 16)),
                           data=data, batch_size=4, lr=1e-3, log_every=1, checkpoint_every=10, eval_every=10,
                           eval_samples=8)
    refiner = RefinerTrainConfig(model=RefinerConfig(), data=data, batch_size=4, lr=1e-3, log_every=1,
                                 checkpoint_every=10, eval_every=5, eval_samples=8)
    return seg, pose, refiner


def tiny_cls_config():
    """A small instance classifier training config for the tiny dataset."""
    from posegrasp.perception.classifier import ClassifierConfig
    from posegrasp.perception.train_cls import ClsTrainConfig

    return ClsTrainConfig(model=ClassifierConfig(widths=(8, 16), crop_size=32), batch_size=16, lr=1e-2,
                          log_every=1, checkpoint_every=10, eval_every=0)


@pytest.fixture(name="tiny_cls_config")
def tiny_cls_config_fixture():
    """``tiny_cls_config()`` as a fixture."""
    return tiny_cls_config()


@pytest.fixture(name="tiny_configs")
def tiny_configs_fixture():
    """``tiny_configs()`` as a fixture: (seg, pose, refiner) training configs."""
    return tiny_configs()


@pytest.fixture(scope="session")
def tiny_run(tiny_bop, tmp_path_factory) -> Path:
    """A run directory with seg/, pose/, refiner/ and cls/ trained for a few steps on the tiny dataset."""
    from posegrasp.perception.train_cls import train_cls
    from posegrasp.perception.train_pose import train_pose
    from posegrasp.perception.train_refiner import train_refiner
    from posegrasp.perception.train_seg import train_seg

    def build(out: Path) -> None:
        seg, pose, refiner = tiny_configs()
        train_seg(tiny_bop, out, seg, steps=15, progress=False)
        train_pose(tiny_bop, out, pose, steps=20, progress=False)
        train_refiner(tiny_bop, out, refiner, steps=5, progress=False)
        train_cls(tiny_bop, out, tiny_cls_config(), steps=60, progress=False)

    return build_once(tmp_path_factory, "tiny_run", build)
