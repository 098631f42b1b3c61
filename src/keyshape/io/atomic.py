"""Atomic file writes (a failed write leaves no half-written file behind, and names its file), staged folders,
and the check every reader makes."""

from __future__ import annotations

import contextlib
import errno
import glob
import json
import os
import shutil
import signal
import sys
import tempfile
import threading
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path

from ..exceptions import InputError, WriteError

__all__ = ["atomic_path", "new_folders", "named_write_errors", "staged_folder", "check_switched", "remove_dead_stages",
           "existing_file", "held_signals", "claimed_folder", "SWITCH"]


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
    with new_folders(path.parent):
        fd, tmp = tempfile.mkstemp(prefix=f".{_room(path.stem, len(path.suffix) + 15)}.", suffix=f".part{path.suffix}",
                                   dir=path.parent)
        os.close(fd)
        tmp = Path(tmp)
        try:
            with named_write_errors(path):
                yield tmp
                os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual permissions
                os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def new_folders(folder: str | Path) -> Iterator[Path]:
    """``folder``, made with its missing parents; when the block fails (an error, Ctrl-C, SIGTERM),
    the folders it made that are still empty are removed again: a stopped command leaves no empty
    output folder behind."""
    folder = Path(folder)
    missing, above = [], folder
    while not above.exists() and above != above.parent:
        missing.append(above)  # the deepest first
        above = above.parent
    try:  # a signal in the middle of making them is a failure of the block too
        folder.mkdir(parents=True, exist_ok=True)
        yield folder
    except BaseException:
        for made in missing:
            try:
                made.rmdir()
            except OSError:  # not empty (or not ours to remove): it and those above stay
                break
        raise


_NO_ROOM = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS})


@contextlib.contextmanager
def named_write_errors(path: str | Path) -> Iterator[None]:
    """Turn a failed write inside the block that names no file (a full disk: ``[Errno 28] No space
    left on device``, a quota, a read-only or failing disk) into a
    :class:`~keyshape.exceptions.WriteError` naming ``path``, the file (or folder) being written."""
    try:
        yield
    except WriteError:
        raise
    except OSError as exc:
        if exc.errno not in _NO_ROOM:
            raise
        error = WriteError(f"{path}: cannot write ({exc.strerror or exc})")
        error.errno = exc.errno
        raise error from exc


SWITCH = ".keyshape-switch"  # in a folder while a stage's files move in: its presence says "incomplete"
def _room(name: str, taken: int, limit: int = 255) -> str:
    """``name`` as the start of a temporary's name that adds ``taken`` bytes: whole when that fits
    the file system's 255-byte names, else cut and ended by a CRC-32 of the whole (so an output
    name that is itself near the limit still gets a temporary beside it, the same one each time)."""
    room = limit - taken
    if len(name.encode()) <= room:
        return name
    tail = f"~{zlib.crc32(name.encode()):08x}"
    return name.encode()[:room - len(tail)].decode(errors="ignore") + tail


_STAGE = ".keyshape-stage"  # the end of every stage folder's name (".<folder>.<random>.keyshape-stage")


@contextlib.contextmanager
def staged_folder(folder: str | Path, *, owned: Callable[[str], bool] | None = None,
                  record: str | None = None) -> Iterator[Path]:
    """Yield a hidden, empty folder beside ``folder``; on success its files move into ``folder``.

    A failure (or Ctrl-C, or SIGTERM through the command line) removes the stage and leaves
    ``folder`` as it was. ``owned(name)`` says which files in ``folder`` an earlier output wrote:
    those the stage did not write again are stale (an earlier run's ``preview.mp4``) and are
    removed after the move; other files are never touched.

    The switch is one step: Ctrl-C and SIGTERM wait until every file is in (:func:`held_signals`),
    so ``folder`` holds the old outputs or the new ones, never a mix. A switch cut short all the
    same (power lost, SIGKILL) is detectable and mended by the next one: while the files move,
    ``folder/.keyshape-switch`` lists every name of either output (:func:`check_switched` refuses
    such a folder, naming it), and the next switch into ``folder`` counts those names as owned, so
    none of the mix survives it. ``record``: the file that says the folder is complete
    (``take.json``); its old copy is removed first and the new one moved in last.

    A stage whose process is gone (killed mid-take: a Ray worker, SIGKILL) is removed by the next
    stage beside it (:func:`remove_dead_stages`): every stage is locked by its process while it lives.
    """
    folder = Path(folder)
    with new_folders(folder.parent):
        remove_dead_stages(folder.parent, folder.name)
        stage = lock = None
        try:
            with held_signals():  # made and locked, or not made: never a stage the finally misses
                stage, lock = _locked_stage(folder)
            yield stage
            written = sorted(p.name for p in stage.iterdir())
            if record in written:
                written = [name for name in written if name != record] + [record]
            with held_signals():
                _switch(stage, folder, written, owned, record)
        finally:
            if stage is not None:
                shutil.rmtree(stage, ignore_errors=True)
                os.close(lock)


def _switch(stage: Path, folder: Path, written: list[str], owned: Callable[[str], bool] | None,
            record: str | None) -> None:
    """Move the files ``written`` from ``stage`` into ``folder`` (``record`` last), remove the stale
    ones, with the journal :data:`SWITCH` in ``folder`` from the first step to the last."""
    folder.mkdir(exist_ok=True)
    cut = _switch_names(folder)  # an earlier switch cut short: its names are ours
    stale = sorted(p.name for p in folder.iterdir() if p.is_file() and p.name not in written and p.name != SWITCH
                   and (p.name in cut or (owned is not None and owned(p.name))))
    journal = {"format": "keyshape-switch", "stage": stage.name, "names": sorted({*written, *stale, *cut})}
    with atomic_path(folder / SWITCH) as tmp:
        tmp.write_text(json.dumps(journal) + "\n")
    if record in written:
        (folder / record).unlink(missing_ok=True)
    for name in written:
        if name == record:
            for old in stale:
                (folder / old).unlink(missing_ok=True)
        (stage / name).replace(folder / name)
    if record not in written:
        for old in stale:
            (folder / old).unlink(missing_ok=True)
    (folder / SWITCH).unlink()


def _switch_names(folder: Path) -> frozenset[str]:
    """The plain file names a cut-short switch into ``folder`` left in its journal (empty if none)."""
    try:
        names = json.loads((folder / SWITCH).read_text()).get("names", [])
    except (OSError, UnicodeDecodeError, ValueError, AttributeError):
        return frozenset()
    return frozenset(n for n in names if isinstance(n, str) and n and n == Path(n).name and n not in (".", ".."))


def check_switched(folder: str | Path) -> None:
    """Raise InputError naming ``folder`` when a switch of staged files into it was cut short
    (its ``.keyshape-switch`` remains): it then holds a mix of two outputs."""
    journal = Path(folder) / SWITCH
    if journal.exists():
        raise InputError(f"{folder}: the last output moved into it was cut short ({journal} remains), so it "
                         "holds a mix of two outputs; run the command that wrote it again")


@contextlib.contextmanager
def claimed_folder(folder: str | Path) -> Iterator[Path]:
    """Hold the output folder ``folder`` for one command, from its start to its end: a second command
    given the same folder meanwhile is refused at once (InputError naming it), before its work, rather
    than both writing it and both saying so. The claim is a locked, empty stage beside ``folder``
    (as :func:`staged_folder` makes), so a claim whose process died is removed by the next one and
    a finished command leaves nothing behind. Where locks are not to be had, nothing is refused."""
    folder = Path(folder)
    with new_folders(folder.parent):
        remove_dead_stages(folder.parent, folder.name)
        claim = lock = None
        try:
            with held_signals():  # made and locked, or not made: never a claim the finally misses
                claim, lock = _locked_stage(folder)
            if _living_stages(folder, but=claim):
                raise InputError(f"{folder}: another keyshape command is writing into it now; wait for it to "
                                 "end or give another output folder")
            yield folder
        finally:
            if claim is not None:
                shutil.rmtree(claim, ignore_errors=True)
                os.close(lock)


def _living_stages(folder: Path, *, but: Path) -> list[Path]:
    """The stages of ``folder`` other than ``but`` whose lock a living process holds."""
    living = []
    for stage in folder.parent.glob(f".{glob.escape(_room(folder.name, len(_STAGE) + 10))}.*{_STAGE}"):
        if stage == but:
            continue
        try:
            fd = os.open(stage, os.O_RDONLY)
        except OSError:
            continue
        try:
            import fcntl

            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:  # held: a living process's
            living.append(stage)
        except (ImportError, OSError):  # no locks here: none can be told alive
            pass
        finally:
            os.close(fd)
    return living


def _locked_stage(folder: Path) -> tuple[Path, int]:
    """A new stage folder beside ``folder`` and a descriptor of it holding its lock (``flock``;
    released when the process ends, however it ends)."""
    while True:
        stage = Path(tempfile.mkdtemp(prefix=f".{_room(folder.name, len(_STAGE) + 10)}.", suffix=_STAGE,
                                     dir=folder.parent))
        try:
            fd = os.open(stage, os.O_RDONLY)
        except FileNotFoundError:  # taken for a dead one's before it was locked
            continue
        if _try_lock(fd) and _same_inode(fd, stage):  # not taken for a dead one's meanwhile
            return stage, fd
        os.close(fd)


def remove_dead_stages(parent: str | Path, name: str | None = None) -> list[Path]:
    """Remove the stage folders in ``parent`` (of the folder ``name``, or of any) whose process is
    gone: their lock is free. Returns them. Without ``fcntl`` (Windows) none can be told dead."""
    found = []
    pattern = f".{glob.escape(_room(name, len(_STAGE) + 10))}.*{_STAGE}" if name is not None else f".*{_STAGE}"
    for stage in Path(parent).glob(pattern):
        try:
            fd = os.open(stage, os.O_RDONLY)
        except OSError:
            continue
        try:
            if stage.is_dir() and not stage.is_symlink() and _try_lock(fd, probe=True) and _same_inode(fd, stage):
                shutil.rmtree(stage, ignore_errors=True)
                found.append(stage)
        finally:
            os.close(fd)
    return found


def _try_lock(fd: int, *, probe: bool = False) -> bool:
    """Take the exclusive lock of ``fd`` without waiting; whether it was free. Where locks are not to
    be had (no ``fcntl``: Windows; a file system without them): True for a stage's own lock, False
    for a probe (a stage cannot be told dead there, so none is removed)."""
    try:
        import fcntl
    except ImportError:
        return not probe
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:  # held: a living process's
        return False
    except OSError:  # ENOLCK, EINVAL...: no locks here
        return not probe
    return True


def _same_inode(fd: int, path: Path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path, follow_symlinks=False)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


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
