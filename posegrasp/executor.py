"""One small interface for work that fans out (scenes, episodes, evaluation frames).

``make_executor(workers)`` gives a local process pool (default) or Ray (``"ray"``, for clusters).
Results come back keyed by task index, so they never depend on how many workers ran them.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, Callable, Iterator, Protocol, Sequence


class Executor(Protocol):
    """Runs ``fn(item)`` for every item and yields ``(index, result)`` as tasks finish."""

    def imap(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]: ...


class SerialExecutor:
    """Runs tasks in this process, in order."""

    def imap(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        for i, item in enumerate(items):
            yield i, fn(item)


class PoolExecutor:
    """A local pool of ``workers`` processes (spawned, so every worker owns its own GL context)."""

    def __init__(self, workers: int):
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = workers

    def imap(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        ctx = mp.get_context("spawn")
        with ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx) as pool:
            futures = {pool.submit(fn, item): i for i, item in enumerate(items)}
            try:
                for fut in as_completed(futures):
                    yield futures[fut], fut.result()
            except BaseException:
                for f in futures:
                    f.cancel()
                raise


class RayExecutor:
    """Ray tasks on an existing cluster (``ray.init(address="auto")``) or a local one."""

    def __init__(self, address: str | None = None):
        import ray  # optional dependency: pip install 'posegrasp[ray]'

        if not ray.is_initialized():
            ray.init(address=address, ignore_reinit_error=True)
        self._ray = ray

    def imap(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        remote = self._ray.remote(fn)
        refs = {remote.remote(item): i for i, item in enumerate(items)}
        pending = list(refs)
        while pending:
            done, pending = self._ray.wait(pending, num_returns=1)
            yield refs[done[0]], self._ray.get(done[0])


def make_executor(workers: int | str | None = None) -> Executor:
    """``None`` -> one process per core; ``1`` -> in-process; ``n`` -> pool of n; ``"ray"`` -> Ray."""
    if workers == "ray":
        return RayExecutor()
    n = (os.cpu_count() or 1) if workers is None else int(workers)
    return SerialExecutor() if n == 1 else PoolExecutor(n)
