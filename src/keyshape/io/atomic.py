"""Atomic file writes (a failed write leaves no half-written file behind), and the check every reader makes."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

from ..exceptions import InputError

__all__ = ["atomic_path", "staged_folder", "existing_file", "held_signals"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path`` in one step.

    On any exception the temporary file is removed and ``path`` is left as it was.
    The temporary name keeps the suffix so writers that dispatch on it still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".part{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual permissions
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def staged_folder(folder: str | Path, *, owned: Callable[[str], bool] | None = None,
                  record: str | None = None) -> Iterator[Path]:
    """Yield a hidden, empty folder beside ``folder``; on success its files move into ``folder``.

    A failure (or Ctrl-C, or SIGTERM through the command line) removes the stage and leaves
    ``folder`` as it was. ``owned(name)`` says which files in ``folder`` an earlier output wrote:
    those the stage did not write again are stale (an earlier run's ``preview.mp4``) and are
    removed after the move; other files are never touched.

    The switch is one step: Ctrl-C and SIGTERM wait until every file is in (:func:`held_signals`),
    so ``folder`` holds the old outputs or the new ones, never a mix. ``record``: the file that
    says the folder is complete (``take.json``); its old copy is removed first and the new one
    moved in last, so a switch cut short all the same (power lost, SIGKILL) leaves a folder
    without it, detectably incomplete.
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        yield stage
        written = sorted(p.name for p in stage.iterdir())
        if record in written:
            written = [name for name in written if name != record] + [record]
        with held_signals():
            folder.mkdir(exist_ok=True)
            if record in written:
                (folder / record).unlink(missing_ok=True)
            for name in written:
                (stage / name).replace(folder / name)
            if owned is not None:
                for old in folder.iterdir():
                    if old.is_file() and old.name not in written and owned(old.name):
                        old.unlink()
    finally:
        shutil.rmtree(stage, ignore_errors=True)


@contextlib.contextmanager
def held_signals(*, waiting: str | None = None) -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM until the block is done, then act on them as they would have.

    For the few steps that must not be cut in two (a folder's switch to its new files, a live
    take written from its spool). A signal that came meanwhile is delivered on leaving, to the
    handler it was meant for (``KeyboardInterrupt``, the command line's ``Terminated``); the
    first one prints ``waiting`` (if given) to stderr. Outside the main thread (where signal
    handlers cannot be set) the block runs as it is.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came: list[int] = []

    def hold(signum, frame) -> None:
        if not came and waiting:
            print(waiting, file=sys.stderr, flush=True)
        came.append(signum)

    kinds = (signal.SIGINT, signal.SIGTERM)
    previous = {kind: signal.signal(kind, hold) for kind in kinds}
    try:
        yield
    finally:
        for kind in kinds:
            signal.signal(kind, previous[kind])
        for kind in dict.fromkeys(came):
            _deliver(kind, previous[kind])


def _deliver(kind: int, handler) -> None:
    """Act on signal ``kind`` as ``handler`` (a Python handler, or the default action) would have."""
    if callable(handler):
        handler(kind, None)
    elif handler == signal.SIG_DFL:
        os.kill(os.getpid(), kind)


def existing_file(path: str | Path) -> Path:
    """``path`` as a Path if it is a file; else InputError naming it."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    return path
