"""Labelled frames per second of BOP dataset generation: 640x480, 5 blocks per scene, every file written.

Times ``generate_dataset`` end to end (worker start-up, scene settling, arm motion, rendering, noise, encoding,
writing) into a fresh temporary folder and prints a table and a JSON line, with the load average of the
machine before and after (other processes on the machine slow this down; say so when you quote the figure),
and the CPU seconds spent per frame by this process and its workers, with the rate they would give if the
worker count of cores were free.
Run: ``MUJOCO_GL=egl .venv/bin/python bench/datagen.py [--workers 2] [--scenes 8] [--views 25]``; with
``--baseline REF [--rounds N]`` also on git ref REF's code, alternating, and the ratio (``bench/baseline.py``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import baseline
from posegrasp.datagen.cli import parse_blocks
from posegrasp.datagen.config import DatagenConfig
from posegrasp.datagen.generate import generate_dataset
from posegrasp.sim.cli import parse_resolution


def _cpu_seconds() -> float:
    """User + system CPU seconds of this process and its waited-for children."""
    import resource

    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                resource.getrusage(resource.RUSAGE_CHILDREN)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--views", type=int, default=25)
    ap.add_argument("--blocks", default="5")
    ap.add_argument("--resolution", default="640x480")
    ap.add_argument("--rgb-format", default="jpg", choices=("jpg", "png"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--msaa", type=int, default=DatagenConfig().msaa, help="colour anti-aliasing samples (0: off)")
    baseline.add_arguments(ap)
    args = ap.parse_args()
    if args.baseline:
        baseline.compare(__file__, sys.argv[1:], args.baseline, "frames_per_s", True, args.rounds,
                         args.baseline_script, "cpu_ms_per_frame")
        return

    w, h = parse_resolution(args.resolution)
    wc = DatagenConfig().workcell
    wc = dataclasses.replace(wc, hand_camera=dataclasses.replace(wc.hand_camera, width=w, height=h))
    cfg = DatagenConfig(blocks=parse_blocks(args.blocks), rgb_format=args.rgb_format, msaa=args.msaa, workcell=wc)
    out = tempfile.mkdtemp(prefix="bench_datagen_")
    load_before = os.getloadavg()
    cpu0 = _cpu_seconds()
    t0 = time.perf_counter()
    try:
        s = generate_dataset(out, args.scenes, args.views, args.seed, cfg, workers=args.workers)
        wall = time.perf_counter() - t0
        cpu = _cpu_seconds() - cpu0
        size_mb = sum(f.stat().st_size for f in Path(out).rglob("*") if f.is_file()) / 1e6
    finally:
        shutil.rmtree(out, ignore_errors=True)
    load_after = os.getloadavg()
    res = {
        "frames_per_s": round(s["images"] / wall, 2),
        "images": s["images"], "scenes": args.scenes, "views": args.views, "workers": args.workers,
        "resolution": args.resolution, "blocks": args.blocks, "rgb_format": args.rgb_format, "msaa": args.msaa,
        "wall_s": round(wall, 2), "dataset_mb": round(size_mb, 1), "cpus": os.cpu_count(),
        # CPU time of this process and its (finished) workers: what the frames cost, whatever else runs
        "cpu_ms_per_frame": round(1000 * cpu / max(s["images"], 1), 1),
        "frames_per_s_if_cores_idle": round(args.workers * s["images"] / max(cpu, 1e-9), 1),
        "load_before": [round(x, 2) for x in load_before], "load_after": [round(x, 2) for x in load_after],
        "unreachable_views": s["views"]["out_of_reach"] + s["views"]["unreachable"] + s["views"]["blocked"],
    }
    width = max(len(k) for k in res)
    for k, v in res.items():
        print(f"{k:<{width}}  {v}")
    print(json.dumps(res))


if __name__ == "__main__":
    main()
