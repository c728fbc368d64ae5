"""Helpers shared by the tests: the command line in a child process, success floors for short trial runs taken
from documented 200-episode measurements, and session fixtures built once for all the run's worker processes."""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Callable

import zygote

from posegrasp.grasping.stats import wilson

#: Documented success counts (successes, episodes), seed 0, `--workers 2`; the floors below are taken from them.
#: Measured by `posegrasp trials --episodes 200 --seed 0 --perception oracle --workers 2` (docs/benchmarks.md).
PICK_PLACE_ORACLE = (200, 200)
#: Measured by `posegrasp trials --episodes 200 --seed 0 --perception model --workers 2` (docs/benchmarks.md).
PICK_PLACE_MODEL = (200, 200)
#: Measured by `posegrasp trials --task kitting --episodes 200 --seed 0 --perception oracle --workers 2`
#: (docs/benchmarks.md).
KITTING_ORACLE = (198, 200)
#: Measured by `posegrasp trials --task stack --episodes 200 --seed 0 --perception oracle --workers 2` (docs/benchmarks.md).
STACK_ORACLE = (194, 200)


def success_floor(k: int, n: int, m: int, alpha: float = 0.01) -> int:
    """Fewest successes an ``m``-episode run must reach, given ``k`` of ``n`` documented successes.

    With ``p`` the lower end of the Wilson 95 % interval of ``k / n`` (a rate the product reaches on any CPU
    unless the measurement was unlucky), the floor is the largest ``f`` with ``P(X < f) <= alpha`` for
    ``X ~ Binomial(m, p)``: a correct product fails the test with probability at most ``alpha``.
    """
    if m < 1:
        raise ValueError(f"need m >= 1 episodes, got {m}")
    p = wilson(k, n)[0]
    below = 0.0  # P(X < f)
    for f in range(m + 1):
        at = math.comb(m, f) * p**f * (1 - p) ** (m - f)
        if below + at > alpha:
            return f
        below += at
    return m


def cli(*args: str) -> list[str]:
    """The command line running ``posegrasp ARGS`` with this interpreter."""
    return [sys.executable, "-m", "posegrasp.cli", *args]


def run_cli(*args: str, timeout: float = 300, cwd: str | Path | None = None, env: dict[str, str] | None = None
            ) -> subprocess.CompletedProcess:
    """``posegrasp ARGS`` run in a child process in ``cwd`` (default: this process's), its output captured as text;
    forked from this process's fork server (``zygote.shared``), so it pays no start-up imports, or, given ``env`` (the
    whole environment: a ``PYTHONPATH`` takes effect only in a new interpreter), started afresh.
    ``subprocess.TimeoutExpired`` past ``timeout`` s."""
    if env is not None:
        return subprocess.run(cli(*args), capture_output=True, text=True, timeout=timeout, cwd=cwd, env=env)
    o = zygote.shared().run(list(args), Path(cwd or os.getcwd()), timeout)
    if o.hung:
        raise subprocess.TimeoutExpired(cli(*args), timeout, o.stdout, o.stderr)
    return subprocess.CompletedProcess(cli(*args), o.rc, o.stdout, o.stderr)


def build_once(tmp_path_factory, name: str, build: Callable[[Path], object]) -> Path:
    """The folder ``name`` that ``build(folder)`` fills, built once per test run: under ``pytest -n`` (xdist) the
    workers share it (the first builds it while the others wait on a lock), else it is the process's own."""
    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # the run's folder, shared by workers
    target, built = root / name, root / f"{name}.built"
    with FileLock(str(root / f"{name}.lock")):
        if not built.exists():
            shutil.rmtree(target, ignore_errors=True)
            target.mkdir(parents=True)
            build(target)
            built.touch()
    return target


def refused(capsys, argv: list[str], words: str, code: int = 2) -> str:
    """Run ``posegrasp argv`` in this process (``posegrasp.cli.main``, as the entry point runs it): exit ``code``,
    one stderr line holding ``words``, no traceback; the line."""
    from posegrasp.cli import main

    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == code, err
    assert len(lines) == 1 and "Traceback" not in err, err
    assert words in lines[0], lines[0]
    return lines[0]
