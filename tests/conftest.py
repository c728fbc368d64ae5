"""Shared test set-up: headless EGL rendering, fixed thread counts."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
