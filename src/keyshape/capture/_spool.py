"""The tracker's spool: what each frame gave, appended to files on disk while a video is tracked.

Flat memory however long the video is: landmarks, scores, head matrices and the hands found in
front of the face (:mod:`~keyshape.capture.visibility`, 672 bytes a frame) are read back as
memory maps.
"""

from __future__ import annotations

import shutil
import tempfile
import typing
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Self

import numpy as np

from ..io.atomic import named_write_errors

__all__ = ["N_LANDMARKS", "N_SCORES", "HANDS_SHAPE", "Spool", "spool_folder"]

N_LANDMARKS = 478
N_SCORES = 52
HANDS_SHAPE = (4, 21, 2)  # a frame's hands (HandTracker's N_HANDS, N_HAND_POINTS; xy pixels)
_NO_HANDS = np.full(HANDS_SHAPE, np.nan, np.float32)


@contextmanager
def spool_folder(parent: Path | None = None) -> Iterator[Path]:
    """A new ``keyshape-track-*`` folder in ``parent`` (None: the system's temporary folder) for
    a take's spools, removed with everything in it when the block ends, however it ends.

    Not ``tempfile.TemporaryDirectory``: a Ctrl-C or SIGTERM landing while it removes the
    folder stops the removal half way and leaves the rest behind. Here the removal is finished
    first, then the interrupt goes on.
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


class Spool:
    """Append-only float32 files on disk, read back as memory maps (flat memory)."""

    SHAPES: typing.ClassVar[dict] = {"points": (N_LANDMARKS, 3), "scores": (N_SCORES,), "matrix": (4, 4),
                                     "hands": HANDS_SHAPE}

    def __init__(self, folder: Path):
        self.folder = folder
        self.files = {}
        self._open = ExitStack()
        self.n_frames = 0
        self.n_faces = 0
        self.n_hands = 0  # frames in which a hand was found
        self.most_seen = 0  # the most faces seen in one frame
        self.index: list[int] = []  # source frame numbers (16 bytes a frame with the times)
        self.ms: list[int] = []

    def append(self, frame) -> None:
        """Write one frame: ``points``, ``scores``, ``matrix`` and ``hands`` (None: none looked
        for) arrays, its source frame ``index``, time ``ms`` and ``n_seen`` faces."""
        hands = _NO_HANDS if frame.hands is None else frame.hands
        with named_write_errors(self.folder):  # a full disk says where
            for name, fh in self.files.items():
                value = hands if name == "hands" else getattr(frame, name)
                fh.write(np.ascontiguousarray(value, dtype=np.float32).tobytes())
        self.n_frames += 1
        self.n_faces += bool(np.isfinite(frame.points[0, 0]))
        self.n_hands += bool(np.isfinite(hands[:, 0, 0]).any())
        self.most_seen = max(self.most_seen, frame.n_seen)
        self.index.append(frame.index)
        self.ms.append(frame.ms)

    def clock(self) -> dict[str, np.ndarray]:
        """``frame_index`` (n_frames,) int and ``time`` (n_frames,) seconds."""
        return {"frame_index": np.array(self.index, dtype=np.int64),
                "time": np.array(self.ms, dtype=np.float64) / 1000.0}

    def __enter__(self) -> Self:
        with ExitStack() as stack:  # a failed open closes the ones before it
            self.files = {name: stack.enter_context(open(self.folder / f"{name}.f32", "wb")) for name in self.SHAPES}
            self._open = stack.pop_all()
        return self

    def __exit__(self, *exc) -> None:
        with named_write_errors(self.folder):  # the last buffered bytes
            self._open.close()

    def arrays(self) -> dict[str, np.ndarray]:
        """Memory maps of what was written (call after the ``with`` block)."""
        return {name: np.memmap(self.folder / f"{name}.f32", dtype=np.float32, mode="r",
                                shape=(self.n_frames, *shape)) for name, shape in self.SHAPES.items()}
