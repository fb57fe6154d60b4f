"""Independent jobs on local processes or on a Ray cluster, with the same results either way.

A job is a module-level function and its arguments; each one writes its own output atomically
(a temporary file, then a rename) and returns a small summary. Nothing a job computes depends
on where or when it runs, only on its arguments (seeds included), so a set of jobs gives the
same files on one process, on N processes or on a cluster; a lost worker costs its job only,
and a rerun makes what is missing.

Ray is an optional extra (``pip install 'deepsync[ray]'``). ``ray`` is what ``ray.init`` takes
as its address: ``auto`` joins the cluster this machine is part of (``ray start --head`` on
one node, ``ray start --address=HEAD:6379`` on the others), ``ray://HEAD:10001`` reaches a
remote cluster through Ray Client (``pip install 'ray[client]'``), and ``local`` starts a Ray
instance on this machine alone. Every node needs this version of deepsync installed and the
output directory on storage every node sees (a shared filesystem).
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any

RAY_HINT = "install it with: pip install 'deepsync[ray]'"


def check_ray_address(address: str) -> str:
    """``address`` as ``ray.init`` takes it, or ValueError naming the choices."""
    if address in ("auto", "local") or address.startswith("ray://") or ":" in address:
        return address
    raise ValueError(f"--ray {address!r}: give auto (the cluster this machine belongs to), local (a Ray "
                     "instance on this machine), ray://HOST:10001 (Ray Client) or HOST:PORT")


class JobRunner:
    """Runs jobs in this process (``workers`` 1), in ``workers`` local processes, or as Ray
    tasks when ``ray`` names a cluster (the cluster then decides how many run at once)."""

    def __init__(self, workers: int = 1, ray: str | None = None) -> None:
        self.workers = max(1, int(workers))
        self.ray = None if ray is None else check_ray_address(ray)

    @property
    def description(self) -> str:
        if self.ray is not None:
            return f"Ray cluster {self.ray}"
        return "this process" if self.workers == 1 else f"{self.workers} local processes"

    def map(self, function: Callable[..., Any], jobs: Sequence[tuple]) -> Iterator[Any]:
        """``function(*job)`` for every job, yielded as they finish (in any order). An error or
        an interrupt stops the rest: finished outputs stay, queued jobs are cancelled."""
        if not jobs:
            return iter(())
        if self.ray is not None:
            return _on_ray(self.ray, function, jobs)
        if self.workers == 1 or len(jobs) == 1:
            return (function(*job) for job in jobs)
        return _on_processes(min(self.workers, len(jobs)), function, jobs)


def _on_processes(workers: int, function: Callable[..., Any], jobs: Sequence[tuple]) -> Iterator[Any]:
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = [pool.submit(function, *job) for job in jobs]
        try:
            for future in as_completed(futures):
                yield future.result()
        except BaseException:  # Ctrl-C or a failure: finished jobs stay, queued ones go
            pool.shutdown(wait=True, cancel_futures=True)
            raise


def _on_ray(address: str, function: Callable[..., Any], jobs: Sequence[tuple]) -> Iterator[Any]:
    try:
        import ray
    except ModuleNotFoundError:
        raise ValueError(f"--ray needs the ray package: {RAY_HINT}") from None
    started = not ray.is_initialized()
    if started:
        ray.init(address=None if address == "local" else address, include_dashboard=False,
                 log_to_driver=False, configure_logging=False)
    # one CPU per job; a job whose worker dies is run again elsewhere (max_retries)
    task = ray.remote(num_cpus=1, max_retries=3)(function)
    pending = [task.remote(*job) for job in jobs]
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    finally:
        if started:
            ray.shutdown()
