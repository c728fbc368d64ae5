"""A hand-camera renderer that keeps one GL context for the whole process.

``sim.camera.CameraRenderer`` makes a new ``mujoco.Renderer`` (a new EGL context) per workcell. On Mesa's
llvmpipe a new context costs about 0.1 s per scene: its shaders are compiled again on the first draw.
Trials render one new scene per episode, so ``EpisodeCamera`` keeps a single context per process and
only makes the model's ``MjrContext`` per scene (measured: ~25 ms instead of ~130 ms before the first frame).
"""

from __future__ import annotations

import mujoco
from mujoco.rendering.classic import gl_context

from posegrasp.sim.camera import CameraRenderer, intrinsics
from posegrasp.sim.config import CameraConfig, RenderConfig

_CONTEXT: list = []  # the process's GL context, made on first use and never freed


class _SharedContextRenderer(mujoco.Renderer):
    """``mujoco.Renderer`` (MuJoCo 4.0) drawing in the process's shared GL context; ``close`` frees only
    the model's ``MjrContext``."""

    def __init__(self, model: mujoco.MjModel, height: int, width: int):
        if not _CONTEXT:
            _CONTEXT.append(gl_context.GLContext(width, height))
        self._gl_context = _CONTEXT[0]
        self._gl_context.make_current()
        self._width, self._height, self._model = width, height, model
        self._scene = mujoco.MjvScene(model=model, maxgeom=10000)
        self._scene_option = mujoco.MjvOption()
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._mjr_context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150.value)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._mjr_context)
        self._mjr_context.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._depth_rendering = self._segmentation_rendering = False

    def close(self) -> None:
        if self._mjr_context is not None:
            self._gl_context.make_current()
            self._mjr_context.free()
            self._mjr_context = None


class EpisodeCamera(CameraRenderer):
    """``CameraRenderer`` (same images, same ``capture``) on the shared GL context."""

    def __init__(self, workcell, camera: str, c: CameraConfig, render: RenderConfig):
        self.wc, self.camera = workcell, camera
        self.cam_id = workcell.camera_ids[camera]
        self.near, self.far = c.near, c.far
        self.K = intrinsics(c.width, c.height, c.fovy_deg)
        self.renderer = _SharedContextRenderer(workcell.model, c.height, c.width)
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = render.shadows
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = render.reflections
        self.option = mujoco.MjvOption()

