"""posegrasp: a simulation testbed for vision-guided robotic grasping."""

import os
from pathlib import Path

from posegrasp import assets as _assets

__version__ = "0.1.0"

#: The shipped assets (block catalogue, scene settings, calibration, weights), installed inside the package.
ASSETS = Path(_assets.__file__).resolve().parent


def _dm_control_renderer_off() -> None:
    """Import dm_control's renderer switched off, before anything imports dm_control: on import it opens a GL
    display for its own renderer (EGL: ``eglInitialize``), which posegrasp never uses (MuJoCo's contexts render,
    ``posegrasp.gl``), and a process holding a display cannot fork workers that render (``posegrasp.executor``).
    ``MUJOCO_GL`` itself stays as set, for MuJoCo; a program that renders with dm_control imports it first."""
    saved = os.environ.get("MUJOCO_GL")
    os.environ["MUJOCO_GL"] = "disable"
    try:
        import dm_control._render  # noqa: F401
    except ImportError:  # dm_control missing: nothing opens a display
        pass
    finally:
        if saved is None:
            del os.environ["MUJOCO_GL"]
        else:
            os.environ["MUJOCO_GL"] = saved


_dm_control_renderer_off()
