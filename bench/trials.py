"""Grasp-and-place throughput: episodes per minute with oracle perception and 2 worker processes.

Runs a fresh campaign (worker start-up included) into a temporary folder and prints the wall-clock rate of
the whole command (summary and report included), that of its episodes alone, the success count, the mean
simulated time per episode, the mean wall time per phase and the CPU time per episode (the rate the workers
would reach on otherwise idle cores), then a JSON line.
Run: ``MUJOCO_GL=egl .venv/bin/python bench/trials.py [EPISODES] [WORKERS] [TASK]`` (defaults 60, 2 and
pick-place; TASK is a ``--task``: pick-place, kitting or stack).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from rich.console import Console

from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.runfolder import TIMINGS, read_records
from posegrasp.grasping.trials import run_trials


def main(episodes: int = 60, workers: int = 2, task: str = "pick-place") -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        s = run_trials(Path(tmp), episodes, seed=1000, perception="oracle", workers=workers,
                       cfg=dataclasses.replace(TrialConfig(), task=task),
                       console=Console(stderr=True, quiet=True))
        wall = time.perf_counter() - t0
        phases: dict[str, float] = {}
        cpu = 0.0
        for rec in read_records(Path(tmp) / TIMINGS).values():
            for k, v in rec["wall_s"].items():
                phases[k] = phases.get(k, 0.0) + v / episodes
            cpu += sum(rec["cpu_s"].values()) / episodes
    out = {"task": task, "episodes": episodes, "workers": workers, "wall_s": round(wall, 2),
           "episodes_per_min": round(60 * episodes / wall, 1),
           "episode_loop_per_min": round(s["wall"]["episodes_per_min"], 1), "success": s["success"],
           "mean_sim_time_s": round(s["mean_sim_time_s"], 2),
           "mean_wall_per_phase_s": {k: round(v, 4) for k, v in phases.items()},
           "mean_cpu_per_episode_s": round(cpu, 4),
           "cpu_bound_episodes_per_min": round(60 * workers / cpu, 1),
           "cpu_load_1min": os.getloadavg()[0]}
    print(f"{episodes} oracle {task} episodes with {workers} workers: {wall:.1f} s = {out['episodes_per_min']} episodes/min "
          f"({s['success']} succeeded; {out['mean_sim_time_s']} s simulated per episode; "
          f"1-min load average {out['cpu_load_1min']:.1f})")
    print(f"the episodes alone (worker start-up included, the summary and the report's re-simulated frames not): "
          f"{s['wall']['seconds']:.1f} s = {out['episode_loop_per_min']} episodes/min")
    print(f"CPU time {cpu:.3f} s per episode in the workers: {out['cpu_bound_episodes_per_min']} episodes/min "
          f"if {workers} cores were free for them (the wall rate above includes worker start-up and other load)")
    for k, v in out["mean_wall_per_phase_s"].items():
        print(f"  {k:10s} {1000 * v:7.1f} ms wall per episode")
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3]), *sys.argv[3:4])
