"""One small interface for work that fans out (scenes, episodes, evaluation frames).

``make_executor(workers)`` gives a local process pool (default) or Ray (``"ray"``, for clusters).
Results come back keyed by task index, so they never depend on how many workers ran them. Tasks return
their results to the caller, which alone writes files: a worker needs no access to the output folder (a Ray
node needs no shared filesystem), and a worker whose parent is gone has nothing to write. Pool workers also
die with their parent, whatever kills it (``die_with_parent``). Inside a ``with`` block an executor keeps its
workers between ``imap`` calls: a trial campaign's warm pool also re-simulates the frames of its report. Ctrl-C
(SIGINT to the whole process group) reaches the parent alone: pool workers ignore it, and the parent ends them
when it stops, so no worker prints a traceback.
"""

from __future__ import annotations

import atexit
import ctypes
import gc
import multiprocessing as mp
import os
import signal
import socket
import sys
import threading
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, Callable, Iterator, Protocol, Self, Sequence

from posegrasp.errors import UserError
from posegrasp.io import flush_output

#: ``prctl`` option asking the kernel to signal this process when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1
#: Environment variables a Ray worker gets from the driver (headless rendering backend).
RAY_ENV = ("MUJOCO_GL", "PYOPENGL_PLATFORM")
#: Mesa llvmpipe's rasteriser threads per GL context (default: one per core).
RENDER_THREADS_ENV = "LP_NUM_THREADS"


class Executor(Protocol):
    """Runs ``fn(item)`` for every item and yields ``(index, result)`` as tasks finish. Used as a context
    manager, it keeps its workers between ``imap`` calls (a pool's warm processes) until the block ends."""

    def imap(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]: ...

    def __enter__(self) -> "Executor": ...

    def __exit__(self, *exc: object) -> None: ...


class _NothingToKeep:
    """An executor without workers of its own to keep: its ``with`` block only hands it back."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        return None


class SerialExecutor(_NothingToKeep):
    """Runs tasks in this process, in order."""

    def imap(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        for i, item in enumerate(items):
            yield i, fn(item)


def die_with_parent(parent: int, sig: signal.Signals = signal.SIGKILL) -> None:
    """Pool worker initializer: SIGINT ignored (the parent handles Ctrl-C), and the kernel sends this process ``sig``
    when ``parent`` dies (Linux ``prctl(PR_SET_PDEATHSIG)``; elsewhere nothing is set); a parent already gone ends it
    at once. Its own exit skips the interpreter's teardown (``_exit_without_teardown``)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    atexit.register(_exit_without_teardown)
    if not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, sig, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent:  # the parent died before the prctl call
        os._exit(1)


def _pool_worker(parent: int, rasterisers: int) -> None:
    """Pool worker initializer: ``die_with_parent``, and software rendering on ``rasterisers`` threads
    (``render_threads``) unless the environment sets them."""
    os.environ.setdefault(RENDER_THREADS_ENV, str(rasterisers))
    die_with_parent(parent)


def render_threads(workers: int) -> int:
    """Mesa llvmpipe's rasteriser threads for each of ``workers`` processes sharing this machine's cores: their share
    of the cores, or 0 (rasterise on the drawing thread) for a core or less. Its default, a thread per core, only adds
    switching (5 % of dataset generation's CPU), and one thread of its own only hand-offs (8-12 % of a scene's time);
    the images are the same."""
    share = (os.cpu_count() or 1) // workers
    return share if share > 1 else 0


def _exit_without_teardown() -> None:
    """A pool worker's exit: the exit handlers registered while it worked have run (this one runs after them),
    stdout and stderr are flushed, and it ends with status 0 without the interpreter's teardown (0.2 s of freeing
    torch, SciPy and MuJoCo, per worker at the end of every pool). Its results went back to the parent as tasks
    finished, and a worker only ends this way once the pool stops it."""
    flush_output()
    os._exit(0)


#: Modules whose import opens a GL display: dm_control's renderers (``posegrasp`` imports it switched off).
DISPLAY_MODULES = ("dm_control._render.pyopengl.egl_renderer", "dm_control._render.glfw_renderer")


def fork_is_safe() -> bool:
    """Whether pool workers may be forked from this process (Linux): it runs one thread (a fork copies the others'
    locks, not them), has loaded no torch (its thread pools do not survive a fork), opened no GL display (on GPU
    drivers a child cannot render through its parent's: none of MuJoCo's EGL, ``posegrasp.gl``'s contexts or
    ``DISPLAY_MODULES``) and started no process (a plug-in's host: a worker would inherit its handles but could not
    use them)."""
    if not sys.platform.startswith("linux") or threading.active_count() > 1 or "torch" in sys.modules \
            or any(m in sys.modules for m in DISPLAY_MODULES):
        return False
    egl, gl = sys.modules.get("mujoco.egl"), sys.modules.get("posegrasp.gl")
    return (getattr(egl, "EGL_DISPLAY", None) is None and not (gl is not None and gl.holds_context())
            and not mp.active_children())


class PoolExecutor:
    """A local pool of ``workers`` processes that die with this process. They are forked where that is safe
    (``fork_is_safe``), all at once as the pool opens, before this process starts another thread, and start with
    this process's modules, which a spawned worker first imports (about 0.7 s of CPU each); this process's objects
    are kept out of their garbage collections (``gc.freeze``), which would otherwise write to, and so copy, every
    page holding one. Elsewhere they are spawned, so that each owns its GL context and torch threads."""

    def __init__(self, workers: int):
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = workers
        self._pool: ProcessPoolExecutor | None = None  # kept between imap calls inside a with block

    def _new_pool(self) -> ProcessPoolExecutor:
        method = "fork" if fork_is_safe() else "spawn"
        pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=mp.get_context(method),
                                   initializer=_pool_worker, initargs=(os.getpid(), render_threads(self.workers)))
        if method == "fork":
            gc.freeze()
            pool.submit(int)  # forks every worker now
            gc.unfreeze()
        return pool

    def __enter__(self) -> "PoolExecutor":
        self._pool = self._new_pool()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        pool, self._pool = self._pool, None
        if pool is None:
            return
        if exc_type is not None and issubclass(exc_type, KeyboardInterrupt):
            _stop_now(pool)
        else:  # an error or the end: the tasks not started are dropped, the running ones finish
            pool.shutdown(cancel_futures=True)

    def imap(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        if self._pool is not None:
            yield from self._run(self._pool, fn, items)
            return
        with self:
            yield from self._run(self._pool, fn, items)

    @staticmethod
    def _run(pool: ProcessPoolExecutor, fn: Callable[[Any], Any], items: Sequence[Any]
             ) -> Iterator[tuple[int, Any]]:
        # no future is cancelled here: the pool's exit does that, or ends the workers on Ctrl-C
        futures = {pool.submit(fn, item): i for i, item in enumerate(items)}
        for fut in as_completed(futures):
            yield futures[fut], fut.result()


def _stop_now(pool: ProcessPoolExecutor) -> None:
    """Ctrl-C: end ``pool``'s workers now (their results are unwanted) and wait for its manager thread to see them
    gone. No future is cancelled first: the manager thread of a broken pool sets an exception on every pending
    future, and one cancelled under it raises ``InvalidStateError`` in that thread (a traceback on stderr)."""
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        proc.kill()
    pool.shutdown(wait=True)


def _check_reachable(address: str) -> None:
    """A one-line UserError unless a ``HOST:PORT`` cluster address accepts a connection within 5 s (``ray.init``
    itself retries for ever); ``auto``, ``ray://`` and an empty address are left to Ray."""
    host, sep, port = address.rpartition(":")
    if not sep or "://" in address or not port.isdigit():
        return
    try:
        socket.create_connection((host, int(port)), timeout=5).close()
    except OSError as e:
        raise UserError(f"cannot reach the Ray cluster at RAY_ADDRESS={address!r} ({e.strerror or e}); start it "
                        "with 'ray start --head' or unset RAY_ADDRESS") from None


class RayExecutor(_NothingToKeep):
    """Ray tasks on an existing cluster (``RAY_ADDRESS``, or ``ray.init`` called before) or a new local one.
    Results travel back to the driver through Ray's object store; the driver's ``MUJOCO_GL`` and
    ``PYOPENGL_PLATFORM`` go to the workers."""

    def __init__(self, address: str | None = None):
        try:
            import ray  # optional dependency: pip install 'posegrasp[ray]'
        except ImportError:
            raise UserError("--workers ray needs Ray: pip install 'posegrasp[ray]' (on every node)") from None
        if not ray.is_initialized():
            _check_reachable(address or os.environ.get("RAY_ADDRESS", ""))
            # worker logs stay in Ray's session folder, out of the progress bar's way
            ray.init(address=address, include_dashboard=False, log_to_driver=False)
        self._ray = ray

    def imap(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        env = {k: os.environ[k] for k in RAY_ENV if k in os.environ}
        remote = self._ray.remote(fn).options(runtime_env={"env_vars": env} if env else None)
        refs = {remote.remote(item): i for i, item in enumerate(items)}
        pending = list(refs)
        try:
            while pending:
                done, pending = self._ray.wait(pending, num_returns=1)
                yield refs[done[0]], self._ray.get(done[0])
        except BaseException:
            for ref in pending:
                self._ray.cancel(ref, force=True)
            raise


def make_executor(workers: int | str | None = None) -> Executor:
    """``None`` -> one process per core; ``1`` -> in-process; ``n`` -> pool of n; ``"ray"`` -> Ray."""
    if workers == "ray":
        return RayExecutor()
    n = (os.cpu_count() or 1) if workers is None else int(workers)
    return SerialExecutor() if n == 1 else PoolExecutor(n)
