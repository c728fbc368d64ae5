"""Grasp-and-place throughput: episodes per minute with oracle perception and 2 worker processes.

Runs a fresh campaign (worker start-up included) into a temporary folder and prints the wall-clock rate of
the whole command (summary and report included), that of its episodes alone, the success count, the mean
simulated time per episode, the mean wall time per phase and the CPU time per episode (the rate the workers
would reach on otherwise idle cores), then a JSON line.
Run: ``MUJOCO_GL=egl .venv/bin/python bench/trials.py [EPISODES] [WORKERS] [TASK] [--task TASK] [--scene SCENE]
[--blocks N] [--seed S] [--perception SPEC] [--hand HAND]`` (defaults 60, 2, pick-place, the task's scene, seed 1000,
oracle, the 3-finger hand; TASK is a ``--task``: pick-place, kitting, stack or bin-pick, whose SCENE is bin or pile;
HAND is 3-finger, 2-finger, suction or hybrid). For bin picking it also prints
the successful picks per wall-clock minute and per simulated hour, percent cleared and attempt success.
With ``--baseline REF [--rounds N]``: also on git ref REF's code, alternating, and the ratio (``bench/baseline.py``).
"""

from __future__ import annotations

import argparse
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

import baseline

from posegrasp.grasping.cli import with_scene
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.runfolder import TIMINGS, read_records
from posegrasp.grasping.trials import Display, run_trials


def main(episodes: int = 60, workers: int = 2, task: str = "pick-place", scene: str | None = None,
         blocks: int | None = None, seed: int = 1000, perception: str = "oracle", hand: str = "3-finger") -> dict:
    cfg = with_scene(dataclasses.replace(TrialConfig(), task=task), scene, blocks)
    cfg = dataclasses.replace(cfg, scene=dataclasses.replace(cfg.scene, workcell=dataclasses.replace(
        cfg.scene.workcell, hand=hand)))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        s = run_trials(Path(tmp), episodes, seed=seed, perception=perception, workers=workers, cfg=cfg,
                       display=Display(Console(stderr=True, quiet=True)))
        wall = time.perf_counter() - t0
        phases: dict[str, float] = {}
        cpu = 0.0
        for rec in read_records(Path(tmp) / TIMINGS).values():
            for k, v in rec["wall_s"].items():
                phases[k] = phases.get(k, 0.0) + v / episodes
            cpu += sum(rec["cpu_s"].values()) / episodes
    out = {"task": task, "hand": hand, "episodes": episodes, "workers": workers, "seed": seed, "perception": perception,
           "wall_s": round(wall, 2), "episodes_per_min": round(60 * episodes / wall, 1),
           "episode_loop_per_min": round(s["wall"]["episodes_per_min"], 1), "success": s["success"],
           "mean_sim_time_s": round(s["mean_sim_time_s"], 2),
           "mean_wall_per_phase_s": {k: round(v, 4) for k, v in phases.items()},
           "mean_cpu_per_episode_s": round(cpu, 4),
           "cpu_bound_episodes_per_min": round(60 * workers / cpu, 1),
           "cpu_load_1min": os.getloadavg()[0]}
    print(f"{episodes} {perception} {task} episodes with {workers} workers: {wall:.1f} s = {out['episodes_per_min']} "
          f"episodes/min ({s['success']} succeeded; {out['mean_sim_time_s']} s simulated per episode; "
          f"1-min load average {out['cpu_load_1min']:.1f})")
    print(f"the episodes alone (worker start-up included, the summary and the report's re-simulated frames not): "
          f"{s['wall']['seconds']:.1f} s = {out['episode_loop_per_min']} episodes/min")
    print(f"CPU time {cpu:.3f} s per episode in the workers: {out['cpu_bound_episodes_per_min']} episodes/min "
          f"if {workers} cores were free for them (the wall rate above includes worker start-up and other load)")
    if "bin_pick" in s:
        b = s["bin_pick"]
        out.update(scene=cfg.bin_pick.scene, parts=list(cfg.bin_pick.clutter.parts),
                   percent_cleared=b["percent_cleared"], attempt_success=b["attempts"], grasp_success=b["grasps"],
                   picks=b["picks"],
                   picks_per_sim_hour=round(b["picks_per_sim_hour"] or 0.0, 1),
                   picks_per_wall_min=round(60 * b["picks"] / s["wall"]["seconds"], 1),
                   cpu_bound_picks_per_min=round(60 * workers * b["picks"] / (cpu * episodes), 1) if cpu else None,
                   attempt_failures=b["attempt_failures"], episode_ends=b["episode_ends"])
        pc = b["percent_cleared"]
        print(f"bin picking ({out['scene']}): cleared {pc['mean']:.1f} % per episode (t 95 % {pc['ci95']}), attempts "
              f"{b['attempts']['success']}/{b['attempts']['n']}, grasps {b['grasps']['success']}/{b['grasps']['n']}; "
              f"{out['picks_per_wall_min']} picks per wall-clock minute "
              f"(episodes alone), {out['cpu_bound_picks_per_min']} if {workers} cores were free; "
              f"{out['picks_per_sim_hour']} picks per simulated hour")
    for k, v in out["mean_wall_per_phase_s"].items():
        print(f"  {k:10s} {1000 * v:7.1f} ms wall per episode")
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("episodes", type=int, nargs="?", default=60)
    p.add_argument("workers", type=int, nargs="?", default=2)
    p.add_argument("task_pos", nargs="?", default=None, metavar="TASK")
    p.add_argument("--task", default=None)
    p.add_argument("--scene", default=None)
    p.add_argument("--blocks", type=int, default=None)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--perception", default="oracle")
    p.add_argument("--hand", default="3-finger")
    baseline.add_arguments(p)
    a = p.parse_args()
    if a.baseline:
        sys.exit(baseline.compare(__file__, sys.argv[1:], a.baseline, "episodes_per_min", True, a.rounds,
                                  a.baseline_script, "mean_cpu_per_episode_s"))
    main(a.episodes, a.workers, a.task or a.task_pos or "pick-place", a.scene, a.blocks, a.seed, a.perception, a.hand)
