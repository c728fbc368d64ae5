"""Where the time goes: one job profiled with cProfile, as a ``.prof`` file and a table of its top costs.

    MUJOCO_GL=egl .venv/bin/python bench/profile.py JOB [--size N] [--out DIR] [--top 25] [--py-spy] [--baseline REF]

JOB, run in this one process (no workers, so the profile sees all of it):
  datagen     ``generate_dataset``: 1 scene of N views (default 25), 640x480, 5 blocks, every file written;
  trials      ``run_trials``: N oracle pick-place episodes (default 4, seed 1000), summary and report included;
  perception  ``bench/perception.py``'s stages on its frame, the shipped model, N frames (default 5) and a warm-up;
  bin-pick    ``run_trials``: N oracle bin-pick episodes in the tote (default 1, seed 0).
The job's main modules are imported, and the perception job's model loaded and frame rendered, before the profile
starts. Writes DIR/JOB.prof (``python -m pstats`` or
snakeviz reads it) and DIR/JOB.txt: the job's wall and CPU seconds,
the 1-min load average, and the top rows by cumulative time and by own time (time in the function itself, C calls
such as MuJoCo's rendering included); prints the latter. ``--py-spy`` (when py-spy is installed) also samples an
unprofiled run of the job into DIR/JOB.svg, a flame graph. DIR defaults to /tmp/posegrasp_profile.
``--baseline REF`` first profiles the same job on git ref REF's code (a worktree, as ``bench/baseline.py`` makes
it; this file runs there, the perception job with REF's own ``bench/perception.py``) into DIR/JOB@SHA.prof and
.txt: the costs before and after, side by side.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

# cProfile imports the standard library's ``profile``, which this file would be with its folder on sys.path
_path = list(sys.path)
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
import cProfile  # noqa: E402

sys.path[:] = _path

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import importlib.util  # noqa: E402
import io  # noqa: E402
import os  # noqa: E402
import pstats  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sysconfig  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

SIZES = {"datagen": 25, "trials": 4, "perception": 5, "bin-pick": 1}


def _datagen(n: int, tmp: Path) -> Callable[[], object]:
    from posegrasp.datagen.config import DatagenConfig
    from posegrasp.datagen.generate import generate_dataset

    return lambda: generate_dataset(tmp / "ds", 1, n, 0, DatagenConfig(), workers=1)


def _trials(n: int, tmp: Path, task: str = "pick-place", seed: int = 1000) -> Callable[[], object]:
    from rich.console import Console

    from posegrasp.grasping.cli import with_scene
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping import trials

    cfg = with_scene(dataclasses.replace(TrialConfig(), task=task), None, None)
    quiet = Console(stderr=True, quiet=True)
    # older code (a --baseline ref) takes the console and the progress flag as arguments of their own
    shown = {"display": trials.Display(quiet)} if hasattr(trials, "Display") else {"console": quiet, "progress": False}
    return lambda: trials.run_trials(tmp / "run", n, seed=seed, perception="oracle", workers=1, cfg=cfg, **shown)


def _perception(n: int, tmp: Path) -> Callable[[], object]:
    """Set-up (the shipped model loaded, the frame rendered) outside the profile; one warm-up frame inside."""
    import torch

    import posegrasp
    from posegrasp import ASSETS
    from posegrasp.perception.estimator import Estimator, EstimatorConfig
    from posegrasp.perception.runtime import one_blas_thread

    # the bench script of the code profiled (a --baseline ref's own)
    script = Path(posegrasp.__file__).resolve().parents[1] / "bench" / "perception.py"
    spec = importlib.util.spec_from_file_location("bench_perception", script)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    torch.set_num_threads(2)
    est = Estimator(ASSETS / "perception" / "model", EstimatorConfig(models=ASSETS / "blocks"))
    frame = bench.sim_frame()
    bench.sim_frame = lambda: frame

    def run() -> None:
        with one_blas_thread():
            bench.bench(est, n, 1)
    return run


#: Per job: its set-up, returning the work to profile.
JOBS = {"datagen": _datagen, "trials": _trials, "perception": _perception,
        "bin-pick": lambda n, tmp: _trials(n, tmp, "bin-pick", 0)}
#: Modules each job imports before its profile starts (their import time is no part of a job's steady state).
IMPORTS = {"datagen": ("posegrasp.datagen.generate", "trimesh"),
           "trials": ("posegrasp.grasping.trials", "posegrasp.grasping.cli"),
           "perception": (),
           "bin-pick": ("posegrasp.grasping.trials", "posegrasp.grasping.cli")}


def _where(file: str) -> str:
    """``file`` shortened: relative to the repository or to site-packages, built-ins as ``~``."""
    import posegrasp

    tree = Path(posegrasp.__file__).resolve().parents[1]  # the checkout profiled (a --baseline ref's worktree)
    for base in (Path(sysconfig.get_paths()["purelib"]), tree, Path(sysconfig.get_paths()["stdlib"])):
        try:
            return str(Path(file).resolve().relative_to(base.resolve()))
        except ValueError:
            continue
    return file


def table(stats: pstats.Stats, sort: str, top: int) -> str:
    """The ``top`` rows of ``stats`` by ``sort`` (``cumulative`` or ``tottime``): calls, own s, cumulative s, % of
    the total, function."""
    total = max(stats.total_tt, 1e-9)
    key = 3 if sort == "cumulative" else 2
    rows = sorted(stats.stats.items(), key=lambda kv: kv[1][key], reverse=True)[:top]
    out = [f"{'calls':>9} {'own s':>8} {'cum s':>8} {'% total':>8}  function (by {sort})"]
    for (file, line, fn), (_, nc, tt, ct, _) in rows:
        name = fn if file == "~" else f"{_where(file)}:{line}({fn})"
        out.append(f"{nc:9d} {tt:8.2f} {ct:8.2f} {100 * (ct if key == 3 else tt) / total:8.1f}  {name}")
    return "\n".join(out)


def _cpu() -> float:
    t = os.times()
    return t.user + t.system


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("job", choices=sorted(JOBS))
    ap.add_argument("--size", type=int, default=None, help="views, episodes or frames (defaults: "
                    + ", ".join(f"{k} {v}" for k, v in SIZES.items()) + ")")
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "posegrasp_profile")
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--py-spy", action="store_true", help="also a py-spy flame graph DIR/JOB.svg")
    ap.add_argument("--baseline", metavar="REF", help="first profile the job on git ref REF's code")
    ap.add_argument("--plain", action="store_true", help=argparse.SUPPRESS)  # the job alone (under py-spy)
    ap.add_argument("--stem", help=argparse.SUPPRESS)  # the files' name (default: JOB)
    args = ap.parse_args(argv)
    n = args.size or SIZES[args.job]
    if args.py_spy and not shutil.which("py-spy"):
        ap.error("--py-spy: py-spy is not installed (pip install py-spy)")
    args.out.mkdir(parents=True, exist_ok=True)
    if args.baseline:
        _profile_ref(args.baseline, [args.job, "--size", str(n), "--out", str(args.out), "--top", str(args.top)])
    with tempfile.TemporaryDirectory() as tmp:
        for m in IMPORTS[args.job]:
            importlib.import_module(m)
        s0 = time.perf_counter()
        work = JOBS[args.job](n, Path(tmp))
        setup = time.perf_counter() - s0
        if args.plain:
            work()
            return 0
        load, w0, c0, prof = os.getloadavg()[0], time.perf_counter(), _cpu(), cProfile.Profile()
        prof.runcall(work)
        wall, cpu = time.perf_counter() - w0, _cpu() - c0
    stem = args.out / (args.stem or args.job)
    prof.dump_stats(stem.with_suffix(".prof"))
    stats = pstats.Stats(prof, stream=io.StringIO())
    head = (f"bench/profile.py {args.job} --size {n}: {wall:.1f} s wall, {cpu:.1f} s CPU (this process), 1-min load "
            f"{load:.2f} before, {os.getloadavg()[0]:.2f} after; set-up before the profile {setup:.1f} s")
    own = table(stats, "tottime", args.top)
    stem.with_suffix(".txt").write_text(f"{head}\n\n{table(stats, 'cumulative', args.top)}\n\n{own}\n")
    print(f"{head}\n\n{own}\n\nwrote {stem}.prof and {stem}.txt (with the top rows by cumulative time)")
    if args.py_spy:
        subprocess.run(["py-spy", "record", "--output", str(stem.with_suffix(".svg")), "--", sys.executable,
                        __file__, args.job, "--size", str(n), "--plain"], check=True)
        print(f"wrote {stem}.svg")
    return 0


def _profile_ref(ref: str, argv: list[str]) -> None:
    """Run this file with ``argv`` on git ref ``ref``'s code, its files named JOB@SHA."""
    import baseline

    sha = baseline.git("rev-parse", "--short", f"{ref}^{{commit}}")
    with baseline.checkout(ref) as tree:
        env = {**os.environ, "PYTHONPATH": str(tree)}
        baseline.check_side(f"{ref} ({sha})", tree, env)
        print(f"== {ref} ({sha})", flush=True)
        subprocess.run([sys.executable, __file__, *argv, "--stem", f"{argv[0]}@{sha}"], env=env, check=True)
    print("== current", flush=True)


if __name__ == "__main__":
    sys.exit(main())
