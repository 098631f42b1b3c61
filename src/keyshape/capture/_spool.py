"""The tracker's spool: what each frame gave, appended to files on disk while a video is tracked.

Flat memory however long the video is: landmarks, scores and head matrices are read back as
memory maps; the frames' colour patches (:mod:`~keyshape.capture.visibility`, 143 kB a frame,
read while tracking so that the visibility needs no second decode) are read a slice at a time.
A spool joined from the segments of a parallel run (:mod:`keyshape.capture._parallel`) reads
its patches from the segments' files.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Self

import numpy as np

from .visibility import PATCH_GRID

__all__ = ["N_LANDMARKS", "N_SCORES", "PATCH_SHAPE", "Spool", "Patches", "room_for_patches", "spool_folder"]

N_LANDMARKS = 478
N_SCORES = 52
PATCH_SHAPE = (N_LANDMARKS, PATCH_GRID ** 2, 3)  # a frame's colour patches
PATCH_BYTES = int(np.prod(PATCH_SHAPE)) * 4
_NAN_PATCHES = np.full(PATCH_SHAPE, np.nan, np.float32)


@contextmanager
def spool_folder(parent: Path | None = None) -> Iterator[Path]:
    """A new ``keyshape-track-*`` folder in ``parent`` (None: the system's temporary folder) for
    a take's spools, removed with everything in it when the block ends, however it ends.

    Not ``tempfile.TemporaryDirectory``: a Ctrl-C or SIGTERM landing while it removes the
    folder (a parallel run's segments hold gigabytes of patches) stops the removal half way and
    leaves the rest behind. Here the removal is finished first, then the interrupt goes on.
    """
    folder = Path(tempfile.mkdtemp(prefix="keyshape-track-", dir=parent))
    try:
        yield folder
    finally:
        try:
            shutil.rmtree(folder, ignore_errors=True)
        except BaseException:  # KeyboardInterrupt, Terminated
            shutil.rmtree(folder, ignore_errors=True)
            raise


def room_for_patches(folder: Path, n_frames: int) -> bool:
    """Whether ``n_frames`` frames' patches take at most half the free space in ``folder``
    (otherwise the visibility decodes the video again instead; 0 frames: the length is unknown)."""
    return n_frames * PATCH_BYTES <= shutil.disk_usage(folder).free / 2


class Spool:
    """Append-only float32 files on disk, read back as memory maps (flat memory).

    patches : whether the frames' patches are written too (to ``patches.f32``). A spool joined
    from others writes none but lists their rows in ``pieces``.
    """

    def __init__(self, folder: Path, *, patches: bool = True):
        self.folder = folder
        self.files = {}
        self.keeps_patches = patches
        self.pieces: list[tuple[Path, int, int]] = []  # (folder, first row, n_rows) whose patches are ours
        self._patches = None
        self._open = ExitStack()
        self.n_frames = 0
        self.n_faces = 0
        self.most_seen = 0  # the most faces seen in one frame
        self.index: list[int] = []  # source frame numbers (16 bytes a frame with the times)
        self.ms: list[int] = []

    def append(self, frame) -> None:
        """Write one frame: ``points``, ``scores``, ``matrix`` and ``patches`` (None: NaN) arrays,
        its source frame ``index``, time ``ms`` and ``n_seen`` faces."""
        for name, fh in self.files.items():
            fh.write(np.ascontiguousarray(getattr(frame, name)).tobytes())
        if self._patches is not None:
            patches = _NAN_PATCHES if frame.patches is None else frame.patches
            self._patches.write(np.ascontiguousarray(patches, dtype=np.float32).tobytes())
        self.n_frames += 1
        self.n_faces += bool(np.isfinite(frame.points[0, 0]))
        self.most_seen = max(self.most_seen, frame.n_seen)
        self.index.append(frame.index)
        self.ms.append(frame.ms)

    def clock(self) -> dict[str, np.ndarray]:
        """``frame_index`` (n_frames,) int and ``time`` (n_frames,) seconds."""
        return {"frame_index": np.array(self.index, dtype=np.int64),
                "time": np.array(self.ms, dtype=np.float64) / 1000.0}

    def __enter__(self) -> Self:
        with ExitStack() as stack:  # a failed open closes the ones before it
            self.files = {name: stack.enter_context(open(self.folder / f"{name}.f32", "wb"))
                          for name in ("points", "scores", "matrix")}
            if self.keeps_patches:
                self._patches = stack.enter_context(open(self.folder / "patches.f32", "wb"))
            self._open = stack.pop_all()
        return self

    def __exit__(self, *exc) -> None:
        self._open.close()

    def arrays(self) -> dict[str, np.ndarray]:
        """Memory maps of what was written (call after the ``with`` block)."""
        shapes = {"points": (N_LANDMARKS, 3), "scores": (N_SCORES,), "matrix": (4, 4)}
        return {name: np.memmap(self.folder / f"{name}.f32", dtype=np.float32, mode="r",
                                shape=(self.n_frames, *shape)) for name, shape in shapes.items()}

    def patches(self) -> Patches | None:
        """The frames' patches, ``(n_frames, *PATCH_SHAPE)``; None if they were not kept."""
        if self.pieces:
            return Patches(self.pieces)
        return Patches([(self.folder, 0, self.n_frames)]) if self.keeps_patches else None


class Patches:
    """Rows of patch files read as one ``(n_rows, *PATCH_SHAPE)`` float32 array, a slice or an
    index array at a time (``patches[i:j]``, ``patches[rows]``). Read, not memory-mapped: a long
    take's patches would otherwise all end up in the resident set.

    pieces : (folder, first row, n_rows) of each ``patches.f32``, in order
    """

    def __init__(self, pieces: list[tuple[Path, int, int]]):
        self.pieces = [piece for piece in pieces if piece[2] > 0]
        self.starts = np.cumsum([0] + [n for _, _, n in self.pieces])
        self.shape = (int(self.starts[-1]), *PATCH_SHAPE)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, rows) -> np.ndarray:
        rows = np.arange(self.shape[0])[rows]
        out = np.empty((len(rows), *PATCH_SHAPE), np.float32)
        if not len(rows):
            return out
        piece = np.searchsorted(self.starts, rows, side="right") - 1
        # runs of consecutive rows in one file, each read at once
        cuts = np.flatnonzero((np.diff(rows) != 1) | (np.diff(piece) != 0)) + 1
        with ExitStack() as stack:
            files = {}
            for lo, hi in zip([0, *cuts], [*cuts, len(rows)]):
                k = int(piece[lo])
                if k not in files:
                    files[k] = stack.enter_context(open(self.pieces[k][0] / "patches.f32", "rb"))
                files[k].seek((self.pieces[k][1] + int(rows[lo] - self.starts[k])) * PATCH_BYTES)
                files[k].readinto(memoryview(out[lo:hi]).cast("B"))
        return out
