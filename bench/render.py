"""Rendering and physics throughput of the workcell on this machine (one thread).

Prints a table and a JSON line: frames/s for RGB, depth and masks from the hand camera at the look pose
at 320x240 and 640x480 (5 blocks), and physics steps/s with the arm and 1, 3 and 5 blocks.
Run: ``MUJOCO_GL=egl .venv/bin/python bench/render.py``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

from posegrasp.sim.camera import CameraRenderer  # noqa: E402
from posegrasp.sim.scene import make_scene  # noqa: E402
from posegrasp.sim.workcell import HAND_CAMERA  # noqa: E402


def rate(fn, min_time: float = 1.0) -> float:
    """Calls per second of ``fn`` over at least ``min_time`` seconds (after one warm-up call)."""
    fn()
    n, t0 = 0, time.perf_counter()
    while (dt := time.perf_counter() - t0) < min_time:
        fn()
        n += 1
    return n / dt


def main() -> None:
    results: dict[str, float] = {}
    scene = make_scene(0, 5)
    wc = scene.workcell
    wc.drive_arm(wc.look_q)
    for w, h in ((320, 240), (640, 480)):
        r = CameraRenderer(wc, HAND_CAMERA, dataclasses.replace(wc.cfg.hand_camera, width=w, height=h))
        for kind in ("rgb", "depth", "mask"):
            results[f"{kind}_{w}x{h}_fps"] = rate(getattr(r, kind))
        r.close()
    for n in (1, 3, 5):
        s = make_scene(1, n).workcell
        results[f"physics_{n}_blocks_steps_per_s"] = rate(lambda: s.step(100)) * 100
    width = max(len(k) for k in results)
    for k, v in results.items():
        print(f"{k:<{width}}  {v:10.1f}")
    print(json.dumps({k: round(v, 1) for k, v in results.items()}))


if __name__ == "__main__":
    main()
