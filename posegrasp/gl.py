"""The process's OpenGL contexts: one for every MuJoCo renderer, and pyrender's renderers kept alive.

``mujoco.Renderer`` makes (and on ``close`` destroys) a GL context per instance. On Mesa's llvmpipe a new
context costs about 0.1 s, as its shaders are compiled again on the first draw, and trials and dataset
generation render a new scene per episode or scene. So the process makes one context (EGL, OSMesa or GLFW as
``MUJOCO_GL`` says) on first use and keeps it until it exits; each renderer only makes its model's
``MjrContext`` (~25 ms instead of ~130 ms before the first frame). Worker processes are spawned, so each owns
its context. ``mjr_render`` draws into whichever framebuffer is bound, so a renderer binds its own offscreen
buffer (``bind_offscreen``) before every draw: several renderers may share the context at once.

pyrender (the tests' reference renderer) makes its own EGL context per
``OffscreenRenderer``; deleting one calls ``eglTerminate`` on the EGL display that MuJoCo's context lives on,
so ``pyrender_renderer`` keeps one per size for the whole process and never frees it.
"""

from __future__ import annotations

import functools

import mujoco
import numpy as np

from posegrasp.errors import ConfigError


@functools.lru_cache(maxsize=1)
def _context() -> "mujoco.GLContext":
    ctx = mujoco.GLContext(64, 64)  # offscreen rendering goes to MuJoCo's own framebuffer objects
    ctx.make_current()
    return ctx


def holds_context() -> bool:
    """Whether this process has made a GL context here: its own (``make_current``) or a kept pyrender renderer."""
    return _context.cache_info().currsize > 0 or pyrender_renderer.cache_info().currsize > 0


def make_current() -> None:
    """Make the process's GL context current (created on first use; another library may have switched)."""
    _context().make_current()


def check_offscreen_size(model: mujoco.MjModel, width: int, height: int) -> None:
    """Raise ConfigError (a ValueError) unless ``width`` x ``height`` px fits the model's offscreen buffer."""
    g = model.vis.global_
    if width > g.offwidth or height > g.offheight:
        raise ConfigError(f"{width}x{height} exceeds the model's offscreen buffer {g.offwidth}x{g.offheight}")


def scene_capacity(model: mujoco.MjModel) -> int:
    """The geoms an ``MjvScene`` of ``model`` holds: room for every geom and site twice over, at least 1000.
    ``mujoco.Renderer``'s 10000 cost about 12 ms to allocate, per renderer, on this product's scenes."""
    return max(1000, 2 * (model.ngeom + model.nsite))


def bind_offscreen(con: mujoco.MjrContext) -> None:
    """Direct drawing and reading to ``con``'s offscreen buffer (the process's GL context being current)."""
    mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, con)


def mjr_context(model: mujoco.MjModel, samples: int | None = None) -> mujoco.MjrContext:
    """An ``MjrContext`` for ``model`` rendering offscreen with ``samples`` multisamples per pixel (None: the model's
    ``offsamples``), in the current GL context. A single-sampled one is made 6 ms faster and read 8 ms faster at
    640x480, and draws the same segmentation (MuJoCo draws labels without multisampling)."""
    saved = model.vis.quality.offsamples
    if samples is not None:
        model.vis.quality.offsamples = samples
    try:
        return mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100.value)
    finally:
        model.vis.quality.offsamples = saved


class Renderer(mujoco.Renderer):
    """``mujoco.Renderer`` (MuJoCo 4.0) drawing in the process's GL context; ``close`` frees only the model's
    ``MjrContext``."""

    def __init__(self, model: mujoco.MjModel, height: int, width: int, samples: int | None = None):
        """A renderer of ``width`` x ``height`` px with ``samples`` multisamples per pixel (``mjr_context``)."""
        self._mjr_context = None  # (``close`` runs from ``__del__`` even if this raises)
        check_offscreen_size(model, width, height)
        self._gl_context = _context()
        self._gl_context.make_current()
        self._width, self._height, self._model = width, height, model
        self._scene = mujoco.MjvScene(model=model, maxgeom=scene_capacity(model))
        self._scene_option = mujoco.MjvOption()
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._mjr_context = mjr_context(model, samples)
        bind_offscreen(self._mjr_context)
        self._mjr_context.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._depth_rendering = self._segmentation_rendering = False

    def render(self, *, out=None):
        """``mujoco.Renderer.render`` into this model's offscreen buffer."""
        if self._mjr_context is not None:
            make_current()
            bind_offscreen(self._mjr_context)
        return super().render(out=out)

    def read_segments(self) -> np.ndarray:
        """A segmentation render of the scene (``update_scene`` first), as ``render`` makes it, read raw: (H, W, 3)
        uint8, each pixel's colour its geom's segid + 1 (little-endian RGB, 0 the background), rows bottom first.
        ``render``'s own mapping to (object id, type) pairs takes twice as long as the render."""
        make_current()
        bind_offscreen(self._mjr_context)
        flags = self._scene.flags
        saved = flags.copy()
        flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
        try:
            mujoco.mjr_render(self._rect, self._scene, self._mjr_context)
            out = np.empty((self._height, self._width, 3), np.uint8)
            mujoco.mjr_readPixels(out, None, self._rect, self._mjr_context)
        finally:
            np.copyto(flags, saved)
        return out

    def close(self) -> None:
        if self._mjr_context is not None:
            make_current()
            self._mjr_context.free()
            self._mjr_context = None


@functools.lru_cache(maxsize=None)
def pyrender_renderer(width: int, height: int):
    """pyrender's ``OffscreenRenderer`` of ``width`` x ``height`` px, made once per process and never freed."""
    import pyrender  # optional dependency: pip install 'posegrasp[render]'

    return pyrender.OffscreenRenderer(width, height)
