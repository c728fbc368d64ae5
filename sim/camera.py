"""Rendering RGB, metric depth and instance masks from a workcell camera, in the OpenCV convention.

This is the one place that converts MuJoCo's camera frame (x right, y up, looking along -z) to OpenCV's
(x right, y down, z forward): ``T_world_cv = T_world_mj @ T_CV_MJ``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import mujoco
import numpy as np

from posegrasp.geometry import R_to_quat, axis_angle_R, invert
from posegrasp import gl
from posegrasp.sim.config import CameraConfig, RenderConfig

#: Pose of the OpenCV camera frame in the MuJoCo camera frame (flip y and z); it is its own inverse.
T_CV_MJ = np.diag([1.0, -1.0, -1.0, 1.0])


def rpy_deg_to_R(rpy_deg) -> np.ndarray:
    """Rotation from extrinsic x-y-z angles in degrees: Rz @ Ry @ Rx."""
    r, p, y = np.deg2rad(rpy_deg)
    return axis_angle_R([0, 0, 1], y) @ axis_angle_R([0, 1, 0], p) @ axis_angle_R([1, 0, 0], r)


def intrinsics(width: int, height: int, fovy_deg: float) -> np.ndarray:
    """K (3x3, pixels) of a MuJoCo camera: fx = fy = 0.5 H / tan(fovy / 2), principal point at the centre."""
    f = 0.5 * height / np.tan(np.deg2rad(fovy_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


@dataclass
class Frame:
    """One RGB-D capture with its labels.

    rgb (H, W, 3) uint8; depth (H, W) float32 metres along the optical axis, 0 where invalid (both None in a
    labels-only capture, ``CameraRenderer.capture(images=False)``: what the oracles read);
    mask (H, W) uint16 with 0 background and k for scene block k; K (3, 3); T_world_cam (4, 4, OpenCV);
    T_cam_obj (K, 4, 4) for every block of the scene, visible or not; obj_ids (K,) catalogue ids.
    """

    rgb: np.ndarray | None
    depth: np.ndarray | None
    mask: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray
    T_cam_obj: np.ndarray
    obj_ids: np.ndarray
    extra: dict = field(default_factory=dict)


def instances(scene: mujoco.MjvScene, seg: np.ndarray, geom_instance: np.ndarray) -> np.ndarray:
    """Instance ids (H, W) uint16 of ``seg`` (H, W, 3) uint8, a segmentation render of ``scene``
    (``gl.Renderer.read_segments``: each pixel's colour is its geom's segid + 1, little-endian RGB, 0 the
    background): the geom's ``geom_instance`` (k for block k), 0 on the background."""
    n = scene.ngeom
    lut = np.zeros(max(n + 2, 256), np.uint16)
    geom_t = int(mujoco.mjtObj.mjOBJ_GEOM)
    for g in scene.geoms[:n]:
        if g.segid >= 0 and g.objtype == geom_t:
            lut[g.segid + 1] = geom_instance[g.objid]
    if n + 1 < 256:  # one byte holds every id
        return cv2.LUT(np.ascontiguousarray(seg[..., 0]), lut[:256])  # (6x numpy's indexing)
    ids = seg[..., 0].astype(np.int32) | (seg[..., 1].astype(np.int32) << 8) | (seg[..., 2].astype(np.int32) << 16)
    return lut[np.minimum(ids, n + 1)]


class CameraRenderer:
    """Offscreen renderer for one camera of a workcell, in the process's GL context (``posegrasp.gl``); reuse it for
    many frames, ``close()`` frees the model's GL resources."""

    def __init__(self, workcell, camera: str, c: CameraConfig, render: RenderConfig = RenderConfig(),
                 antialias: bool = True):
        """The renderer of ``camera`` with its settings ``c`` (size, field of view, depth range) and ``render``;
        ``antialias`` False: single-sampled, for masks alone (the same masks, made and read faster; colour edges
        jagged)."""
        self.antialias = antialias
        self.wc = workcell
        self.camera = camera
        self.cam_id = workcell.camera_ids[camera]
        self.near, self.far = c.near, c.far
        self.K = intrinsics(c.width, c.height, c.fovy_deg)
        self.renderer = gl.Renderer(workcell.model, height=c.height, width=c.width, samples=None if antialias else 0)
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = render.shadows
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = render.reflections
        self.option = mujoco.MjvOption()  # groups 0-2 visible: collision primitives (group 3) are hidden

    def close(self) -> None:
        self.renderer.close()

    def _update(self) -> None:
        self.renderer.update_scene(self.wc.data, camera=self.cam_id, scene_option=self.option)

    def rgb(self) -> np.ndarray:
        """Colour image (H, W, 3) uint8."""
        self.renderer.disable_depth_rendering()
        self.renderer.disable_segmentation_rendering()
        self._update()
        return self.renderer.render().copy()

    def depth(self) -> np.ndarray:
        """Metric depth along the optical axis (H, W) float32; 0 outside [near, far] and on background."""
        self.renderer.disable_segmentation_rendering()
        self.renderer.enable_depth_rendering()
        self._update()
        d = self.renderer.render().astype(np.float32)
        self.renderer.disable_depth_rendering()
        d[(d < self.near) | (d > self.far)] = 0.0
        return d

    def mask(self) -> np.ndarray:
        """Instance mask (H, W) uint16: 0 background and robot, k where block k is visible."""
        self._update()
        return instances(self.renderer.scene, self.renderer.read_segments()[::-1], self.wc.geom_instance)

    def capture(self, images: bool = True) -> Frame:
        """RGB, depth and mask of the current state, with K, the camera pose and every block's ``T_cam_obj``;
        ``images=False``: the mask and the poses only (no RGB or depth is rendered)."""
        T_world_cam = self.wc.camera_pose(self.camera)
        T_cam_world = invert(T_world_cam)
        T_cam_obj = np.einsum("ij,kjl->kil", T_cam_world, self.wc.block_poses())
        obj_ids = np.array([b.block.obj_id for b in self.wc.blocks], dtype=int)
        rgb, depth = (self.rgb(), self.depth()) if images else (None, None)
        return Frame(rgb, depth, self.mask(), self.K.copy(), T_world_cam, T_cam_obj, obj_ids)


def add_mjcf_camera(parent, name: str, T_parent_cv: np.ndarray, cam: CameraConfig) -> None:
    """Add to the MJCF body ``parent`` a MuJoCo camera ``name`` (and a site at it, for IK) whose OpenCV frame sits at
    ``T_parent_cv`` (m), with ``cam``'s field of view and resolution."""
    T_parent_mj = T_parent_cv @ T_CV_MJ
    quat = R_to_quat(T_parent_mj[:3, :3])
    parent.add("camera", name=name, pos=T_parent_mj[:3, 3], quat=quat, fovy=cam.fovy_deg,
               resolution=(cam.width, cam.height))
    parent.add("site", name=name, pos=T_parent_mj[:3, 3], quat=quat, size=(0.005,), group=4)
