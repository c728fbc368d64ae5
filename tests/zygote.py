"""A fork server's client: ``posegrasp`` commands run in child processes forked from one that imported the command
line and its heavy libraries once (``tests/zygote_server.py``), so a test pays for a command's work, not for its
start-up's imports (2-4 s each: torch, its compiler's modules, MuJoCo, trimesh).

The child runs the command as the ``posegrasp`` program does (``posegrasp.cli.entry``), in its own session, with the
caller's environment and working folder, stdin from ``/dev/null``: its exit status, output and files are the
command's own.
"""

from __future__ import annotations

import atexit
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

SERVER = Path(__file__).resolve().parent / "zygote_server.py"


@dataclasses.dataclass
class Outcome:
    """A command's exit status, whether it was killed at its time limit, its wall time (s) and its output."""

    rc: int
    hung: bool
    seconds: float
    stdout: str
    stderr: str


class Zygote:
    """One fork server; ``run`` is thread-safe (one command at a time)."""

    def __init__(self) -> None:
        env = dict(os.environ, MUJOCO_GL="egl", PYOPENGL_PLATFORM="egl", PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen([sys.executable, str(SERVER)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True, env=env)
        assert self.proc.stdout.readline().strip() == "ready"
        self.lock = threading.Lock()
        self.tmp = Path(tempfile.mkdtemp(prefix="zygote-"))

    def run(self, argv: list[str], cwd: Path, timeout: float) -> Outcome:
        """``posegrasp ARGV`` in ``cwd`` under the caller's environment, killed with its process group after
        ``timeout`` s (``hung``)."""
        out, err = self.tmp / "stdout", self.tmp / "stderr"
        with self.lock:
            req = {"argv": argv, "cwd": str(Path(cwd).resolve()), "stdout": str(out), "stderr": str(err),
                   "timeout": timeout, "env": dict(os.environ)}
            self.proc.stdin.write(json.dumps(req) + "\n")
            self.proc.stdin.flush()
            ans = json.loads(self.proc.stdout.readline())
            return Outcome(ans["rc"], ans["hung"], ans["seconds"], out.read_text(errors="replace"),
                           err.read_text(errors="replace"))

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(timeout=60)
        shutil.rmtree(self.tmp, ignore_errors=True)


_SHARED: Zygote | None = None


def shared() -> Zygote:
    """This process's fork server, started on first use and closed at exit."""
    global _SHARED
    if _SHARED is None or _SHARED.proc.poll() is not None:
        _SHARED = Zygote()
        atexit.register(_SHARED.close)
    return _SHARED
