"""Ray, the one module that imports it: run batch tasks on local cores or on a cluster.

``keyshape batch`` hands its per-take work to a runner with one method, ``map(fn, items)``,
which yields ``(item, result)`` pairs as tasks finish. :class:`RayRunner` is that runner on Ray:
a private local instance (one worker per core) by default, or an existing cluster given its
address (``ray start --head`` prints it). Workers get ``OPENBLAS_NUM_THREADS=1``: several
processes on few cores each running threaded BLAS slow down 25-50x (DESIGN.md).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from typing import Self

from ..exceptions import MissingDependencyError

__all__ = ["WORKER_ENV", "RayRunner", "ray_available"]

WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "TQDM_DISABLE": "1"}


def _import_ray():
    try:
        import ray
    except ImportError:
        raise MissingDependencyError("ray", extra="ray") from None
    return ray


def ray_available() -> bool:
    """Whether Ray can be imported (without importing it)."""
    import importlib.util

    return importlib.util.find_spec("ray") is not None


class RayRunner:
    """Run tasks on Ray; a context manager that starts (and stops) Ray if it was not running.

    Parameters
    ----------
    workers : number of CPUs of the local instance (default: every core); ignored with ``address``
    address : ``HOST:PORT`` of a running cluster's head (``ray start --head``), or None for a
        private local instance
    """

    name = "ray"

    def __init__(self, *, workers: int | None = None, address: str | None = None):
        self.workers = workers
        self.address = address
        self._ray = None
        self._started = False
        self._depth = 0  # re-entrant: only the outermost exit stops the Ray it started

    def __enter__(self) -> Self:
        ray = self._ray = _import_ray()
        if self._depth == 0 and not ray.is_initialized():
            ray.init(**self._init_kwargs())
            self._started = True
        self._depth += 1
        return self

    def _init_kwargs(self) -> dict:
        runtime_env = {"env_vars": dict(WORKER_ENV)}
        common = {"include_dashboard": False, "log_to_driver": False, "logging_level": "error",
                  "configure_logging": True, "runtime_env": runtime_env}
        if self.address is not None:
            return {"address": self.address, **common}
        # "local": always a private instance, never a cluster found in RAY_ADDRESS or /tmp/ray
        return {"address": "local", "num_cpus": self.workers or os.cpu_count() or 1, **common}

    def __exit__(self, *exc) -> None:
        self._depth -= 1
        if self._depth == 0 and self._started:
            self._ray.shutdown()
            self._started = False

    @property
    def n_workers(self) -> int:
        """CPUs the tasks can use (the cluster's total when joining one)."""
        return int(self._ray.cluster_resources().get("CPU", 1))

    def map(self, fn: Callable, items: Iterable) -> Iterator[tuple[object, object]]:
        """Yield ``(item, fn(item))`` in the order tasks finish; a task whose worker died yields
        ``(item, exception)`` instead (``fn`` itself should catch ordinary errors)."""
        ray = self._ray
        task = ray.remote(num_cpus=1, max_retries=0)(fn)
        pending = {task.remote(item): item for item in items}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                item = pending.pop(ref)
                try:
                    yield item, ray.get(ref)
                except ray.exceptions.RayError as exc:
                    yield item, exc
