"""A fork server (``tests/zygote.py``): imports the ``posegrasp`` command line once, then runs each requested
command in a forked child process of its own (own session, cwd and environment, stdout and stderr to files) under a
time limit.

Requests and answers are JSON lines on stdin and stdout: ``{"argv", "cwd", "stdout", "stderr", "timeout"}`` and
optionally ``"env"`` (the child's whole environment) in,
``{"rc", "hung", "seconds"}`` out. A child past its limit is killed with its process group (``hung``: true); a
child killed by a signal answers ``rc`` = minus the signal's number. The child runs the command as
the ``posegrasp`` program does (``posegrasp.cli.entry``): ``main``'s status is the exit status and an uncaught
exception prints its traceback, so what a user would see is what the harness sees.
"""

from __future__ import annotations

import gc
import json
import os
import signal
import sys
import time
import traceback


def _preload() -> None:
    """Import what the commands import lazily (no threads are started: importing torch starts none)."""
    import importlib

    from posegrasp import cli

    cli.build_parser()
    for name in ("torch", "torch._dynamo", "matplotlib.pyplot", "mujoco", "trimesh", "PIL.Image",
                 "posegrasp.perception.train_seg", "posegrasp.perception.train_pose", "posegrasp.perception.train_cls", "posegrasp.perception.evaluate",
                 "posegrasp.grasping.trials", "posegrasp.bop.check", "posegrasp.bop.show", "posegrasp.objects.show"):
        try:
            importlib.import_module(name)
        except ImportError:
            pass


def _child(req: dict) -> None:
    """In the forked child: run the command and exit with its status (never returns)."""
    os.setsid()
    os.chdir(req["cwd"])
    if "env" in req:
        os.environ.clear()
        os.environ.update(req["env"])
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)
    for fd, key in ((1, "stdout"), (2, "stderr")):
        f = os.open(req[key], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(f, fd)
        os.close(f)
    sys.argv = ["posegrasp", *req["argv"]]
    from posegrasp.cli import entry, exit_now

    try:
        entry()  # exits with the command's status
    except BaseException:  # what the real command prints on its way out
        traceback.print_exc()
        exit_now(1)


def _serve() -> None:
    for line in sys.stdin:
        req = json.loads(line)
        t0 = time.monotonic()
        pid = os.fork()
        if pid == 0:
            try:
                _child(req)
            except BaseException as e:  # the harness's own failure, never the command's
                if isinstance(e, SystemExit):
                    raise
                os._exit(99)
        hung, status = False, 0
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                break
            if time.monotonic() - t0 > req["timeout"]:
                hung = True
                _kill_group(pid)
                _, status = os.waitpid(pid, 0)
                break
            time.sleep(0.05)
        _kill_group(pid)  # workers the command left behind
        rc = os.waitstatus_to_exitcode(status)
        sys.stdout.write(json.dumps({"rc": rc, "hung": hung, "seconds": round(time.monotonic() - t0, 2)}) + "\n")
        sys.stdout.flush()


def _kill_group(pid: int) -> None:
    try:
        os.killpg(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


if __name__ == "__main__":
    _preload()
    # Out of the collector's reach: a child's exit then skips a full collection of torch's objects (2 s), and its
    # reference counts leave those pages shared.
    gc.freeze()
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    _serve()
