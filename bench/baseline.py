"""``--baseline REF`` for the bench scripts: the same benchmark on a git ref's code, in the same run, and the ratio.

Not a benchmark itself. ``compare`` checks REF out into a temporary, detached ``git worktree`` (removed afterwards),
then runs the bench script as child processes of this same Python, alternately on the current code and on REF's
(``rounds`` pairs, the order swapped every round, so drifting load hits both alike), and prints each figure (and its
CPU cost, which other load disturbs less) with the 1-min load average before and after it (the benchmark's own
processes count in it), both medians and the ratio (the median of the rounds' ratios), then a JSON line.

The package maps its parts' folders (``sim/``, ``datagen/``, ...) to ``posegrasp.<part>`` (pyproject's
``package-dir``) and is installed editable, so ``PYTHONPATH=WORKTREE`` alone would import ``posegrasp`` from the
worktree but its parts from the installed checkout. The worktree's ``posegrasp/`` folder gets a link per part
(``posegrasp/sim -> ../sim``), so that ``PYTHONPATH=WORKTREE`` imports all of REF's code, in worker processes too;
each side's imported module files are printed and checked before any run.

``{tree}`` in an option's value stands for the side's checkout (the current one, or REF's worktree), so that each
side reads its own shipped files, such as weights whose format changed since REF. Inputs a script makes with
``shared_input`` (a simulated frame) are made once, by the current code, and read by both sides.

REF runs its own copy of the bench script (the benchmark as REF knew it) unless ``--baseline-script current``; when
its copy rejects an option, the current script file runs on REF's code instead, and the output says so.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: In an option's value, the side's own checkout: ``--weights {tree}/assets/perception/model_bin`` gives each side
#: the weights its code shipped with.
TREE = "{tree}"
#: Environment variable naming a folder both sides of a comparison share, for inputs made once (``shared_input``).
SHARED = "POSEGRASP_BENCH_SHARED"
#: Modules whose files must come from the side's own tree.
PROBES = ("posegrasp", "posegrasp.sim.workcell", "posegrasp.datagen.generate", "posegrasp.perception.estimator",
          "posegrasp.grasping.trials")
#: CPU features the nets' speed turns on (their int8 convolutions above all), by /proc/cpuinfo's names.
FEATURES = {"avx2": "AVX2", "avx512f": "AVX-512", "avx512_vnni": "VNNI", "avx_vnni": "VNNI", "amx_int8": "AMX"}
#: Environment variables that cap the instructions the libraries use, so one CPU stands in for an older one.
ISA_CAPS = ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY", "MKL_ENABLE_INSTRUCTIONS")


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The options ``compare`` reads: ``--baseline REF``, ``--rounds N``, ``--baseline-script own|current``."""
    g = ap.add_argument_group("comparison with another version")
    g.add_argument("--baseline", metavar="REF", help="also run this benchmark on git ref REF's code, alternating "
                   "with the current code, and print both figures and their ratio")
    g.add_argument("--rounds", type=int, default=1, help="with --baseline: pairs of runs (default 1)")
    g.add_argument("--baseline-script", choices=("own", "current"), default="own",
                   help="with --baseline: REF's copy of this script (default) or the current file on REF's code")


def shared_input(name: str, make: Callable[[], tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """``make()``'s arrays, made once per comparison: the first run (the current code's, which goes first) saves them
    as ``name`` (.npz) in the comparison's shared folder, and REF's runs load them, so both sides time the same input
    even where REF's code could not make it. Outside a comparison: ``make()``."""
    folder = os.environ.get(SHARED)
    path = Path(folder) / name if folder else None
    if path is not None and path.is_file():
        with np.load(path) as f:
            return tuple(f[f"a{i}"] for i in range(len(f.files)))
    arrays = make()
    if path is not None:
        np.savez(path, **{f"a{i}": a for i, a in enumerate(arrays)})
    return arrays


def own_argv(argv: Sequence[str]) -> list[str]:
    """``argv`` without the options of ``add_arguments``: what each run of the benchmark gets."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a in ("--baseline", "--rounds", "--baseline-script"):
            skip = True
        elif not a.startswith(("--baseline=", "--rounds=", "--baseline-script=")):
            out.append(a)
    return out


def host() -> dict[str, object]:
    """This machine as a comparison's figures depend on it: CPU model, cores, vector features and any ``ISA_CAPS``."""
    info = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    field = {k.strip(): v.strip() for k, _, v in (ln.partition(":") for ln in info.split("\n\n")[0].splitlines())}
    flags = set(field.get("flags", "").split())
    return {"cpu": field.get("model name", "unknown"), "cores": os.cpu_count(),
            "features": list(dict.fromkeys(name for f, name in FEATURES.items() if f in flags)),
            "caps": {k: os.environ[k] for k in ISA_CAPS if k in os.environ}}


def git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *args], check=True, capture_output=True, text=True).stdout.strip()


@contextlib.contextmanager
def checkout(ref: str) -> Iterator[Path]:
    """A detached worktree of ``ref`` whose ``posegrasp/`` links its parts' folders, with its compiled parts built
    in place (where it has a ``setup.py``), removed on exit."""
    tmp = Path(tempfile.mkdtemp(prefix="posegrasp_baseline_")) / "tree"
    git("worktree", "add", "--detach", "--quiet", str(tmp), ref)
    try:
        dirs = tomllib.loads((tmp / "pyproject.toml").read_text())["tool"]["setuptools"].get("package-dir", {})
        for name, folder in dirs.items():
            part = name.split(".")
            if len(part) == 2 and part[0] == "posegrasp" and not (tmp / "posegrasp" / part[1]).exists():
                (tmp / "posegrasp" / part[1]).symlink_to(Path("..") / folder)
        if (tmp / "setup.py").exists():
            subprocess.run([sys.executable, "setup.py", "-q", "build_ext", "--inplace"], cwd=tmp, check=True,
                           capture_output=True)
        yield tmp
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tmp)], capture_output=True)
        shutil.rmtree(tmp.parent, ignore_errors=True)


def _imported_from(env: dict[str, str]) -> dict[str, str]:
    """The file each of ``PROBES`` is imported from, by a fresh process with ``env`` (links resolved)."""
    code = ("import importlib, json, pathlib; print(json.dumps({m: str(pathlib.Path(importlib.import_module(m)"
            f".__file__).resolve()) for m in {PROBES!r}}}))")
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=tempfile.gettempdir())
    if r.returncode != 0:
        sys.exit(f"cannot import the package with PYTHONPATH={env.get('PYTHONPATH', '')}: "
                 f"{r.stderr.strip().splitlines()[-1]}")
    return json.loads(r.stdout)


def check_side(label: str, tree: Path, env: dict[str, str]) -> None:
    """Exit unless every probe module of ``env``'s process lies in ``tree``; print where they come from."""
    files = _imported_from(env)
    wrong = {m: f for m, f in files.items() if not Path(f).is_relative_to(tree.resolve())}
    if wrong:
        sys.exit(f"{label}: {', '.join(wrong)} imported from {', '.join(set(wrong.values()))}, not from {tree}")
    print(f"{label}: code imported from {tree} ({files['posegrasp.datagen.generate']}, ...)")


def _run(script: Path, argv: list[str], env: dict[str, str]) -> tuple[dict | None, str]:
    """Run ``script argv``: (its last JSON line, or None, and its stderr's last line)."""
    r = subprocess.run([sys.executable, str(script), *argv], env=env, stdout=subprocess.PIPE,
                       stderr=subprocess.PIPE, text=True)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    err = (r.stderr.strip().splitlines() or [f"exit {r.returncode}"])[-1]
    return (json.loads(lines[-1]) if r.returncode == 0 and lines else None), err


def _value(result: dict, key: str) -> float:
    for k in key.split("."):
        result = result[k]
    return float(result)


class _Sides:
    """The two sides of a comparison: script, environment and figures of the current code and of REF's."""

    def __init__(self, script: Path, ref: str, tree: Path, which: str, shared: Path):
        self.script, self.ref = script, ref
        self.env = {"current": {**os.environ, SHARED: str(shared)},
                    "baseline": {**os.environ, SHARED: str(shared), "PYTHONPATH": str(tree)}}
        self.trees = {"current": ROOT, "baseline": tree}
        own = tree / script.relative_to(ROOT)
        self.scripts = {"current": script, "baseline": own if which == "own" and own.is_file() else script}
        self.figures: dict[str, dict[str, list[float]]] = {}
        self.loads: list[list[float]] = []

    def run(self, label: str, side: str, argv: list[str], keys: Sequence[str]) -> None:
        """One run of ``side``; its figures at ``keys`` kept, printed after ``label`` with the 1-min load before and
        after it."""
        l0 = os.getloadavg()[0]
        argv = [a.replace(TREE, str(self.trees[side])) for a in argv]
        res, err = _run(self.scripts[side], argv, self.env[side])
        if res is None and self.scripts[side] != self.script and "unrecognized arguments" in err:
            print(f"{self.ref}'s own {self.script.name} rejects the options ({err}); the current file runs on its code")
            self.scripts[side] = self.script
            res, err = _run(self.script, argv, self.env[side])
        if res is None:
            sys.exit(f"{side} run of {self.scripts[side]} failed: {err}")
        self.loads.append([round(l0, 2), round(os.getloadavg()[0], 2)])
        for k in keys:
            self.figures.setdefault(k, {"current": [], "baseline": []})[side].append(_value(res, k))
        shown = ", ".join(f"{self.figures[k][side][-1]:.2f} {k}" for k in keys)
        print(f"{label} {side:8s} {shown}   1-min load {l0:.2f} -> {self.loads[-1][1]:.2f}", flush=True)

    def how(self) -> str:
        """Which script ran on REF's code."""
        s = self.scripts["baseline"]
        if s == self.script:
            return f"the current {self.script.name} file"
        same = s.read_bytes() == self.script.read_bytes()
        return f"its own {s.name} ({'the same bytes as' if same else 'differs from'} the current file)"


def compare(script: str, argv: Sequence[str], ref: str, key: str, higher_is_better: bool, rounds: int = 1,
            which: str = "own", cpu_key: str | None = None) -> int:
    """Run ``script`` (with ``own_argv(argv)``) on the current code and on ``ref``'s, ``rounds`` pairs, and print the
    machine (``host``), the figure at dotted ``key`` of each run's JSON line (and its CPU cost at ``cpu_key``, lower is
    better), with the load average, then both medians and their ratios."""
    script, argv = Path(script).resolve(), own_argv(argv)
    keys = [key] + ([cpu_key] if cpu_key else [])
    sha = git("rev-parse", "--short", f"{ref}^{{commit}}")
    machine = host()
    print(f"host: {machine['cpu']}, {machine['cores']} cores, {' '.join(machine['features']) or 'no AVX2'}"
          + "".join(f", {k}={v}" for k, v in machine["caps"].items()))
    with checkout(ref) as tree, tempfile.TemporaryDirectory(prefix="posegrasp_bench_inputs_") as shared:
        sides = _Sides(script, ref, tree, which, Path(shared))
        check_side("current", ROOT, sides.env["current"])
        check_side(f"{ref} ({sha})", tree, sides.env["baseline"])
        for r in range(rounds):
            for side in (("current", "baseline") if r % 2 == 0 else ("baseline", "current")):
                sides.run(f"round {r + 1}", side, argv, keys)
        how = sides.how()
    print(f"{ref} ({sha}) ran {how}")
    out = {"ref": ref, "ref_commit": sha, "host": machine, "rounds": rounds, "baseline_script": how,
           "load_1min": sides.loads}
    for k in keys:
        f = sides.figures[k]
        cur, base = statistics.median(f["current"]), statistics.median(f["baseline"])
        pairs = [c / b for c, b in zip(f["current"], f["baseline"])]  # each round's two runs, next to each other
        ratio = statistics.median(pairs)
        faster = ratio if (higher_is_better and k == key) else 1 / ratio
        print(f"{k}: current {cur:.2f}, {ref} {base:.2f} (medians); current/{ref} {ratio:.3f} (median of the rounds' "
              f"{', '.join(f'{x:.3f}' for x in pairs)}): {faster:.2f}x {'as fast' if faster >= 1 else 'the speed'}")
        out[k] = {**f, "ratio": round(ratio, 4), "speedup": round(faster, 4)}
    print(json.dumps(out))
    return 0
