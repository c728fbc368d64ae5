"""Plug-in providers run in a process of their own, so that nothing a plug-in does reaches the campaign.

A ``py:`` or installed provider (``grasping.provider_registry``) is imported, built and asked for estimates in a
child process (``IsolatedProvider``): one that calls ``os._exit`` or ``sys.exit``, crashes (a segfault), changes the
working directory or hangs fails the capture it was asked for (``PerceptionError``) or, at import and factory,
the campaign's start (``ProviderError``), with one line naming the provider, and the next capture gets a fresh
process. The plug-in's loading (its import and factory, once its process runs) and every ``estimate`` call get
``TrialConfig.perception_timeout_s`` wall seconds each (0: no limit); past it the child is killed. Estimates come back as ``Estimate``s; what the plug-in
returned is checked in the child (``checked_estimates``), so its own classes never cross the process boundary.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import multiprocessing.util as mp_util
import os
import signal
import time
from multiprocessing.connection import Connection
from typing import Any, Callable

from posegrasp.errors import PerceptionError, ProviderError


def _why(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _host(conn: Connection, build: Callable[[str, str], Any], spec: str, objects: str, parent: int) -> None:
    """The child's loop: ``build(spec, objects)`` the provider, report its name (or why it cannot be built), then
    answer each ``(obs, seed)`` with ``("ok", estimates)`` or ``("error", what went wrong)``."""
    from posegrasp.executor import die_with_parent
    from posegrasp.grasping.perception import checked_estimates

    os.setpgid(0, 0)  # a process group of its own: whatever the plug-in forks ends with it (``_kill``)
    signal.signal(signal.SIGTERM, lambda *_: os.killpg(0, signal.SIGKILL))
    die_with_parent(parent, signal.SIGTERM)  # a campaign killed (even by SIGKILL) takes the whole group with it
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the campaign's to handle
    conn.send(("ready", None))  # posegrasp is loaded: the plug-in's own time starts
    try:
        provider = build(spec, objects)
    except ProviderError as e:
        conn.send(("error", str(e)))
        return
    except BaseException as e:  # SystemExit, KeyboardInterrupt: a plug-in's, not ours
        conn.send(("error", f"perception {spec!r}: loading it raised {_why(e)}"))
        return
    conn.send(("ok", provider.name))
    while True:
        try:
            obs, seed = conn.recv()
        except EOFError:  # the campaign is gone
            return
        try:
            answer = ("ok", checked_estimates(provider.estimate(obs, seed), None, ""))
        except PerceptionError as e:
            answer = ("error", str(e).strip())
        except BaseException as e:  # anything the plug-in raises, SystemExit included, fails this capture only
            answer = ("error", f"raised {_why(e)[:200]}")
        conn.send(answer)


def _death(proc: Any) -> str:
    """How the child ``proc`` ended: its exit status or the signal that killed it."""
    proc.join(5)
    code = proc.exitcode
    if code is None:
        return "stopped answering"
    if code < 0:
        try:
            return f"crashed (signal {signal.Signals(-code).name})"
        except ValueError:
            return f"crashed (signal {-code})"
    return f"exited with status {code}"


#: Wall seconds a plug-in's process may take to start and load posegrasp, before the plug-in's own time starts.
READY_TIMEOUT_S = 300.0


class IsolatedProvider:
    """A plug-in provider ``spec`` for the object set ``objects``, built by ``build(spec, objects)`` (a module-level
    function) in a child process (see the module's docstring); ``timeout_s`` (None or 0: no limit) bounds loading
    and each ``estimate``."""

    def __init__(self, spec: str, objects: str, timeout_s: float | None, build: Callable[[str, str], Any]):
        self.spec, self.objects, self.timeout_s, self.build = spec, objects, timeout_s, build
        self._proc: Any = None
        self._conn: Connection | None = None
        self.name = self._start()

    def _start(self) -> str:
        """Start the child, wait for it to build the provider; its name, or a one-line ProviderError."""
        ctx = mp.get_context("spawn")
        conn, child = ctx.Pipe()
        proc = ctx.Process(target=_host, args=(child, self.build, self.spec, self.objects, os.getpid()), daemon=True,
                           name="posegrasp-plugin")
        proc.start()
        child.close()
        mp_util.Finalize(self, _kill, args=(proc,), exitpriority=10)  # at the process's exit, the group goes too
        try:
            self._answer(conn, proc, READY_TIMEOUT_S)
            kind, value = self._answer(conn, proc, self.timeout_s)
        except _Gone as e:
            raise ProviderError(f"perception {self.spec!r}: loading it (import and factory) {e}") from None
        if kind != "ok":
            proc.join(5)
            raise ProviderError(value)
        self._proc, self._conn = proc, conn
        return value

    @staticmethod
    def _answer(conn: Connection, proc: Any, timeout_s: float | None) -> tuple[str, Any]:
        """The child's next message within ``timeout_s`` (None or 0: no limit); ``_Gone`` if none comes: the child
        ended (how, even while a process it forked holds the pipe open), or was killed when it ran out of time."""
        end = time.monotonic() + timeout_s if timeout_s else math.inf
        while not conn.poll(min(0.1, max(0.0, end - time.monotonic()))):
            if not proc.is_alive() and not conn.poll(0):
                _kill(proc)
                raise _Gone(_death(proc))
            if time.monotonic() >= end:
                _kill(proc)
                raise _Gone(f"did not finish within {timeout_s:g} s (TrialConfig.perception_timeout_s)")
        try:
            return conn.recv()
        except (EOFError, OSError):
            raise _Gone(_death(proc)) from None

    def estimate(self, obs: Any, seed: int) -> list:
        """The plug-in's checked estimates for ``obs``, from its process (restarted if an earlier call ended it)."""
        if self._proc is None or not self._proc.is_alive():
            self._stop()
            try:
                self._start()
            except ProviderError as e:
                raise PerceptionError(f"could not be restarted: {e}") from None
        try:
            self._conn.send((obs, seed))
            kind, value = self._answer(self._conn, self._proc, self.timeout_s)
        except _Gone as e:
            self._stop()
            raise PerceptionError(f"{e} in estimate") from None
        except BaseException:  # interrupted (a timer, Ctrl-C): the child may still answer, so it goes
            self._stop()
            raise
        if kind != "ok":
            raise PerceptionError(value)
        return value

    def _stop(self) -> None:
        if self._proc is not None:
            _kill(self._proc)
        if self._conn is not None:
            self._conn.close()
        self._proc = self._conn = None


class _Gone(Exception):
    """The plug-in's process ended or ran out of time (the message says which)."""


def _kill(proc: Any) -> None:
    """End the child ``proc`` and its process group (what the plug-in forked)."""
    if proc.pid is not None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except OSError:  # the group is gone (or not made yet)
            pass
    if proc.is_alive():
        proc.kill()
    proc.join(5)
