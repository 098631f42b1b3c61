"""Atomic file writes (a failed write leaves no half-written file behind), and the check every reader makes."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from ..exceptions import InputError

__all__ = ["atomic_path", "staged_folder", "existing_file"]


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
def staged_folder(folder: str | Path, *, owned: Callable[[str], bool] | None = None) -> Iterator[Path]:
    """Yield a hidden, empty folder beside ``folder``; on success its files move into ``folder``.

    A failure (or Ctrl-C, or SIGTERM through the command line) removes the stage and leaves
    ``folder`` as it was. ``owned(name)`` says which names in ``folder`` belong to this kind of
    output: those the stage did not write are stale (an earlier run's ``preview.mp4``) and are
    removed after the move; other files are never touched.
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        yield stage
        written = sorted(p.name for p in stage.iterdir())
        folder.mkdir(exist_ok=True)
        for name in written:
            (stage / name).replace(folder / name)
        if owned is not None:
            for old in folder.iterdir():
                if old.is_file() and old.name not in written and owned(old.name):
                    old.unlink()
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def existing_file(path: str | Path) -> Path:
    """``path`` as a Path if it is a file; else InputError naming it."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    return path
