"""Labelled frames for dataset generation: RGB, metric depth, visible instance masks and amodal masks.

Two MuJoCo render passes per frame (colour; segmentation with the depth buffer read alongside), then each
block rendered alone for its amodal mask, in a viewport cropped to its projected bounding box with the
frustum cropped to match, so the pixels are exactly those of a full-image render of the block alone, at a
fraction of the cost. A block whose silhouette crosses the image border is also rendered beyond it, in tiles
over bop_toolkit's canvas (3x the image's size), for ``scene_gt_info.json``'s whole-silhouette counts. It
draws in the process's GL context (``posegrasp.gl``): each scene only gets new ``MjrContext``s for its model.
"""

from __future__ import annotations

import mujoco
import numpy as np

from posegrasp.geometry import invert, transform_points
from posegrasp import gl
from posegrasp.datagen import sensor
from posegrasp.sim.camera import Frame, instances, intrinsics
from posegrasp.sim.config import CameraConfig, RenderConfig
from posegrasp.sim.workcell import Workcell

_SEG_FLAGS = (mujoco.mjtRndFlag.mjRND_SEGMENT, mujoco.mjtRndFlag.mjRND_IDCOLOR)


class LabelRenderer:
    """Renders labelled frames from one camera of a workcell. ``close()`` frees the model's GL resources.

    Images are (H, W) with OpenCV's K (pixel centres at integer coordinates); depth is metres along the optical
    axis, 0 outside [near, far]; masks are per block k = 1..K (scene order).
    """

    def __init__(self, workcell: Workcell, camera: str, c: CameraConfig, render: RenderConfig = RenderConfig(),
                 msaa: int = 4):
        """The renderer of ``camera`` with its settings ``c`` (size, field of view, depth range), ``render`` and
        ``msaa`` multisamples per colour pixel."""
        m = workcell.model
        width, height = c.width, c.height
        gl.check_offscreen_size(m, width, height)
        self.wc, self.camera = workcell, camera
        self.width, self.height, self.near, self.far = width, height, c.near, c.far
        self.K = intrinsics(width, height, c.fovy_deg)
        gl.make_current()
        # two GL resource sets: multisampled (anti-aliased) for colour, single-sampled for labels and depth
        self.con_rgb, self.con = gl.mjr_context(m, msaa), gl.mjr_context(m, 0)
        self.con.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self.scene = mujoco.MjvScene(m, maxgeom=gl.scene_capacity(m))
        self.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = render.shadows
        self.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = render.reflections
        self.cam = mujoco.MjvCamera()
        self.cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self.cam.fixedcamid = workcell.camera_ids[camera]
        self.option = mujoco.MjvOption()  # groups 0-2: collision primitives (group 3) stay hidden
        self.solo_option = mujoco.MjvOption()  # only group 5, where one block's visual geom is moved
        self.solo_option.geomgroup[:] = 0
        self.solo_option.geomgroup[5] = 1
        self.rect = mujoco.MjrRect(0, 0, width, height)
        # geom ids of each block's visual (rendered) geoms
        vis = (m.geom_group != 3) & (m.geom_rgba[:, 3] > 0)
        self.block_geoms = [np.flatnonzero(vis & (m.geom_bodyid == b)) for b in workcell.block_body]
        # near/far planes of MuJoCo's reversed-Z projection, for depth conversion
        ext = m.stat.extent
        self._znear, self._zfar = np.float32(m.vis.map.znear * ext), np.float32(m.vis.map.zfar * ext)

    def close(self) -> None:
        """Free this model's GL resources (the process's GL context stays)."""
        if self.con is not None:
            gl.make_current()
            self.con.free()
            self.con_rgb.free()
            self.con = self.con_rgb = None

    # -- passes ----------------------------------------------------------------------------------------
    def _update(self, option: mujoco.MjvOption) -> None:
        gl.make_current()  # another library (pyrender) may have switched contexts
        mujoco.mjv_updateScene(self.wc.model, self.wc.data, option, None, self.cam,
                               mujoco.mjtCatBit.mjCAT_ALL.value, self.scene)

    def _set_seg(self, on: bool) -> None:
        """Segmentation colours on/off, and the matching resources bound (single-sampled for labels)."""
        for f in _SEG_FLAGS:
            self.scene.flags[f] = on
        gl.bind_offscreen(self.con if on else self.con_rgb)

    def _metric_depth(self, raw: np.ndarray) -> np.ndarray:
        """Reversed-Z depth buffer (bottom row first) -> metres along the optical axis (as ``mujoco.Renderer``
        does), top row first."""
        zn, zf = self._znear, self._zfar
        c = np.float32(-0.5) * (-(zf + zn) / (zf - zn)) - np.float32(0.5)
        d = np.float32(-0.5) * (-(np.float32(2) * zf * zn) / (zf - zn))
        return sensor.metric_depth(raw, c, d, self.near, self.far)

    def rgb(self) -> np.ndarray:
        """Colour image (H, W, 3) uint8 of the current state."""
        self._update(self.option)
        self._set_seg(False)
        mujoco.mjr_render(self.rect, self.scene, self.con_rgb)
        out = np.empty((self.height, self.width, 3), np.uint8)
        mujoco.mjr_readPixels(out, None, self.rect, self.con_rgb)
        return out[::-1].copy()

    def depth_and_instances(self) -> tuple[np.ndarray, np.ndarray]:
        """Depth (H, W) float32 m and visible instance ids (H, W) uint16 (k for block k, 0 elsewhere)."""
        self._update(self.option)
        self._set_seg(True)
        mujoco.mjr_render(self.rect, self.scene, self.con)
        seg = np.empty((self.height, self.width, 3), np.uint8)
        raw = np.empty((self.height, self.width), np.float32)
        mujoco.mjr_readPixels(seg, raw, self.rect, self.con)
        self._set_seg(False)
        return self._metric_depth(raw), instances(self.scene, seg[::-1], self.wc.geom_instance)

    def amodal(self, T_cam_obj: np.ndarray) -> tuple[list[np.ndarray], list[tuple[int, int, int, int] | None],
                                                   list[tuple[int, tuple[int, int, int, int] | None]]]:
        """Full silhouette (H, W) bool of every block rendered alone at its pose (``T_cam_obj``: (K, 4, 4)), the
        pixel box [x0, x1) x [y0, y1) it was rendered in (None: not in the image), and the silhouette's part
        outside the image on bop_toolkit's canvas (3x the image's size around it): its pixel count and its
        (x_min, y_min, x_max, y_max) in image pixel coordinates (None: no such pixel)."""
        H, W = self.height, self.width
        out, boxes, beyond = [], [], []
        for k, geoms in enumerate(self.block_geoms):
            mask = np.zeros((H, W), bool)
            box, whole = self._bbox(k, T_cam_obj[k], (1, 3))
            boxes.append(box)
            if box is not None:
                x0, y0, x1, y1 = box
                mask[y0:y1, x0:x1] = self._solo(geoms, box)
            out.append(mask)
            beyond.append(self._beyond(geoms, whole) if whole is not None and whole != box else (0, None))
        return out, boxes, beyond

    def _solo(self, geoms: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
        """Silhouette (y1 - y0, x1 - x0) bool of the block made of ``geoms`` alone, in pixel box
        [x0, x1) x [y0, y1) of the image plane (any box no larger than the offscreen buffer, also beyond the
        image)."""
        m = self.wc.model
        x0, y0, x1, y1 = box
        saved = m.geom_group[geoms].copy()
        m.geom_group[geoms] = 5
        self._update(self.solo_option)
        m.geom_group[geoms] = saved
        self._crop_frustum(x0, y0, x1, y1)
        self._set_seg(True)
        rect = mujoco.MjrRect(0, 0, x1 - x0, y1 - y0)
        mujoco.mjr_render(rect, self.scene, self.con)
        sub = np.empty((y1 - y0, x1 - x0, 3), np.uint8)
        mujoco.mjr_readPixels(sub, None, rect, self.con)
        self._set_seg(False)
        return sub[::-1, :, 0] > 0

    def _beyond(self, geoms: np.ndarray, whole: tuple[int, int, int, int]
                ) -> tuple[int, tuple[int, int, int, int] | None]:
        """Pixel count and (x_min, y_min, x_max, y_max) of the silhouette's pixels in box ``whole`` outside the
        image, rendered in tiles of the image's size."""
        H, W = self.height, self.width
        X0, Y0, X1, Y1 = whole
        count, ext = 0, []
        for ty in range(Y0, Y1, H):
            for tx in range(X0, X1, W):
                tile = (tx, ty, min(tx + W, X1), min(ty + H, Y1))
                if tile[0] >= 0 and tile[1] >= 0 and tile[2] <= W and tile[3] <= H:
                    continue  # inside the image: the amodal mask has it
                ys, xs = np.nonzero(self._solo(geoms, tile))
                xs, ys = xs + tx, ys + ty
                out = (xs < 0) | (xs >= W) | (ys < 0) | (ys >= H)
                if out.any():
                    count += int(out.sum())
                    ext.append((xs[out].min(), ys[out].min(), xs[out].max(), ys[out].max()))
        if not ext:
            return 0, None
        e = np.array(ext)
        return count, (int(e[:, 0].min()), int(e[:, 1].min()), int(e[:, 2].max()), int(e[:, 3].max()))

    def _bbox(self, k: int, T_cam_obj: np.ndarray, canvases: tuple[int, ...]
              ) -> list[tuple[int, int, int, int] | None]:
        """Per canvas, the pixel box [x0, x1) x [y0, y1) covering block k's projected vertices (+1 px), clipped to the
        image (canvas 1) or to a canvas that many times its size centred on it (3: bop_toolkit's)."""
        W, H = self.width, self.height
        p = transform_points(T_cam_obj, self.wc.blocks[k].block.vertices)
        if np.all(p[:, 2] <= self._znear):  # behind the GL near plane: not drawn at all
            return [None] * len(canvases)
        cut = np.any(p[:, 2] <= self._znear)  # cut by the near plane: its projection is unbounded
        if not cut:
            uv = p[:, :2] / p[:, 2:] * self.K[[0, 1], [0, 1]] + self.K[:2, 2]
            lo, hi = np.floor(uv.min(axis=0)).astype(int) - 1, np.ceil(uv.max(axis=0)).astype(int) + 2
        out = []
        for c in canvases:
            lo_x, lo_y, hi_x, hi_y = -(c // 2) * W, -(c // 2) * H, (c // 2 + 1) * W, (c // 2 + 1) * H
            if cut:
                out.append((lo_x, lo_y, hi_x, hi_y))
                continue
            x0, y0, x1, y1 = max(int(lo[0]), lo_x), max(int(lo[1]), lo_y), min(int(hi[0]), hi_x), min(int(hi[1]), hi_y)
            out.append((x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None)
        return out

    def _crop_frustum(self, x0: int, y0: int, x1: int, y1: int) -> None:
        """Make the scene's frustum cover only pixel columns [x0, x1) and rows [y0, y1) of the full image.

        MuJoCo's ``frustum_width`` is the half width at the near plane (0: from the viewport's aspect).
        """
        for c in (self.scene.camera[0], self.scene.camera[1]):
            top = c.frustum_top
            s = (top - c.frustum_bottom) / self.height  # near-plane size of one pixel
            left, right = (x0 - self.width / 2) * s, (x1 - self.width / 2) * s
            c.frustum_center = 0.5 * (left + right)
            c.frustum_width = 0.5 * (right - left)
            c.frustum_top, c.frustum_bottom = top - y0 * s, top - y1 * s

    def capture(self) -> Frame:
        """A labelled frame of the current state; ``extra``: per-block full silhouettes ``amodal``, ``boxes`` and
        their parts ``beyond`` the image (``amodal``)."""
        wc = self.wc
        T_world_cam = wc.camera_pose(self.camera)
        T_cam_obj = np.einsum("ij,kjl->kil", invert(T_world_cam), wc.block_poses())
        rgb = self.rgb()
        depth, inst = self.depth_and_instances()
        obj_ids = np.array([b.block.obj_id for b in wc.blocks], dtype=int)
        masks, boxes, beyond = self.amodal(T_cam_obj)
        return Frame(rgb, depth, inst, self.K.copy(), T_world_cam, T_cam_obj, obj_ids,
                     extra={"amodal": masks, "boxes": boxes, "beyond": beyond})
