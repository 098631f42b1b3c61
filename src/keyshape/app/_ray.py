"""Ray, the one module that imports it: run batch tasks on local cores or on a cluster.

``keyshape batch`` hands its per-take work to a runner with one method, ``map(fn, items)``,
which yields ``(item, result)`` pairs as tasks finish. :class:`RayRunner` is that runner on Ray:
a private local instance (one worker per core) by default, or an existing cluster given its
address (``ray start --head`` prints it). Workers get ``OPENBLAS_NUM_THREADS=1``: several
processes on few cores each running threaded BLAS slow down 25-50x (DESIGN.md).

Ray is a guest of the command: the local instance keeps its session files in a temporary folder of
its own, removed when it stops; its C++ crash handler (which answers SIGTERM with a stack dump and
an abort) is left off, and the SIGTERM handler ``ray.init`` sets is replaced by the one it found,
so a stopped batch ends as every command does (``keyshape: terminated``, exit 143).
"""

from __future__ import annotations

import os
import shutil
import signal
import sys
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import Self

from ..exceptions import MissingDependencyError, Terminated

__all__ = ["WORKER_ENV", "RayRunner", "ray_available"]

WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "TQDM_DISABLE": "1"}


def _import_ray():
    try:
        import ray
    except ImportError:
        raise MissingDependencyError("ray", extra="ray") from None
    return ray


_SOCKET = "/keyshape-ray-12345678/session_2026-12-07_13-27-04_079067_1234567/sockets/plasma_store"


def _session_parent() -> str:
    """Where the local instance's temporary folder goes: Ray's own choice (``RAY_TMPDIR``, else the
    temporary directory; ``/tmp`` on macOS), or ``/tmp`` when that is too long for Ray's sockets
    (an AF_UNIX path holds 107 bytes)."""
    parent = os.environ.get("RAY_TMPDIR") or ("/tmp" if sys.platform == "darwin" else tempfile.gettempdir())
    return parent if len(os.fsencode(parent)) + len(_SOCKET) <= 107 else "/tmp"


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
        self._temp_dir: str | None = None  # the local instance's session files

    def __enter__(self) -> Self:
        ray = self._ray = _import_ray()
        if self._depth == 0 and not ray.is_initialized():
            self._init(ray)
            self._started = True
        self._depth += 1
        return self

    def _init(self, ray) -> None:
        """``ray.init``, leaving the process's SIGTERM handler as it was (a SIGTERM meanwhile raises
        :class:`~keyshape.exceptions.Terminated`) and Ray's temporary files in a folder of ours."""
        os.environ.setdefault("RAY_DISABLE_FAILURE_SIGNAL_HANDLER", "1")
        kwargs = self._init_kwargs()
        if self.address is None:
            self._temp_dir = kwargs["_temp_dir"] = tempfile.mkdtemp(prefix="keyshape-ray-", dir=_session_parent())
            # the workers' temporary files (a take's tracking spool) go with the instance's: a
            # worker killed mid-take leaves nothing in the system's temporary folder
            work = os.path.join(self._temp_dir, "work")
            os.mkdir(work)
            kwargs["runtime_env"]["env_vars"]["TMPDIR"] = work
        main = threading.current_thread() is threading.main_thread()
        previous = signal.getsignal(signal.SIGTERM) if main else None
        try:
            ray.init(**kwargs)
        except SystemExit as exc:  # Ray's own SIGTERM handler, set during init
            self._remove_temp_dir()
            if exc.code == signal.SIGTERM:
                raise Terminated() from None
            raise
        except BaseException:
            self._remove_temp_dir()
            raise
        finally:
            if main and previous is not None:
                signal.signal(signal.SIGTERM, previous)

    def _remove_temp_dir(self) -> None:
        if self._temp_dir is not None:
            shutil.rmtree(self._temp_dir, ignore_errors=True)
            self._temp_dir = None

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
            try:
                self._ray.shutdown()
            finally:
                self._started = False
                self._remove_temp_dir()

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
            done = self._wait(list(pending))
            for ref in done:
                item = pending.pop(ref)
                try:
                    yield item, ray.get(ref)
                except ray.exceptions.RayError as exc:
                    yield item, exc

    def _wait(self, refs: list) -> list:
        """The finished ones of ``refs`` (at least one). Ctrl-C and SIGTERM are held while Ray waits
        (a Python exception raised inside its C++ wait comes out as a ``SystemError``) and acted on
        between waits of half a second."""
        from ..io.atomic import held_signals

        while True:
            with held_signals():
                done, _ = self._ray.wait(refs, num_returns=1, timeout=0.5)
            if done:
                return done
