"""Tracking one video on every core: overlapping segments, a landmarker per worker process.

The frames ``start <= i < end`` are cut into one segment per worker, sized so that every worker
tracks the same number of frames. Each segment but the first starts ``overlap`` frames before
its share: MediaPipe's first frame is a face detection and the following ones track from it,
so by the time the share starts the worker's landmarker follows the face as a sequential run
would. A worker seeks to the keyframe before its first frame (:func:`~keyshape.capture.video.frame_pts`)
instead of decoding the video up to it. This process tracks the first segment itself while
the others run in fresh interpreters (:func:`start_workers`), started before the video is even
probed so that their imports overlap this process's.

Stitching keeps the one person followed. Neighbouring segments both tracked the overlap; the
later one is kept only if it followed the same face there (centres within half a face width
over the last frames where both saw one) or, when they share no such frame, if its first face
is one :class:`~keyshape.capture._track.FaceFollower` would have taken for the earlier
segment's last one. Otherwise its share is tracked again here, its follower seeded with that
last face, as the sequential run would have tracked it.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..exceptions import WriteError
from .video import VideoInfo, frame_pts

__all__ = ["default_workers", "plan_segments", "spool_parallel", "start_workers", "stop_workers", "Segment"]

OVERLAP_SECONDS = 0.5  # warm-up of each later segment (at least MIN_OVERLAP frames)
MIN_OVERLAP = 8
_CHUNK = 4096  # frames copied at a time when the segments are joined (memory stays flat)


def default_workers() -> int:
    """One worker per core this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


@dataclass(frozen=True)
class Segment:
    """Frames ``first <= i < end`` tracked by one worker, of which ``share <= i < end`` are kept."""

    first: int
    share: int
    end: int


def plan_segments(start: int, end: int, workers: int, overlap: int) -> list[Segment]:
    """Cut ``start <= i < end`` into at most ``workers`` segments of equal work, warm-up included.

    A segment keeps at least ``3 * overlap`` frames, so short inputs get fewer workers.

    >>> plan_segments(0, 100, 2, 10)
    [Segment(first=0, share=0, end=55), Segment(first=45, share=55, end=100)]
    >>> len(plan_segments(0, 50, 4, 10))
    1
    """
    n = end - start
    workers = max(1, min(workers, (n + overlap) // (4 * overlap)))
    per = -(-(n + (workers - 1) * overlap) // workers)  # frames each worker tracks
    segments, share = [], start
    for _ in range(workers):
        first = max(start, share - overlap)
        stop = min(end, first + per)
        segments.append(Segment(first, share, stop))
        share = stop
    return segments


def _rebuilt(spool_type, folder: Path, state: dict):
    """A spool of ``spool_type`` over what a worker wrote to ``folder`` (``state``: its counters)."""
    spool = spool_type(folder)
    for name, value in state.items():
        setattr(spool, name, value)
    return spool


# --------------------------------------------------------------------------- stitching


def _centres(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Face centres ``(n, 2)`` and widths ``(n,)`` of ``points (n, 478, 3)``; NaN where no face."""
    points = np.asarray(points, dtype=float)
    return points[:, :, :2].mean(axis=1), np.ptp(points[:, :, 0], axis=1)


def _last_face(points: np.ndarray, block: int = 1024) -> tuple[int, np.ndarray, float] | None:
    """(row, centre, width) of the last frame of ``points`` with a face, or None.

    Read backwards ``block`` frames at a time, so a memory map of an hour's segment has only its
    last pages mapped in (about 5.7 kB a frame: the whole would add 250 MB to the resident set)."""
    for stop in range(len(points), 0, -block):
        rows = np.flatnonzero(np.isfinite(points[max(stop - block, 0):stop, 0, 0]))
        if len(rows):
            row = max(stop - block, 0) + int(rows[-1])
            centre, width = _centres(points[row:row + 1])
            return row, centre[0], float(width[0])
    return None


def _same_person(before: np.ndarray, after: np.ndarray, rest: np.ndarray, last, max_jump: float = 1.0) -> bool:
    """Did the later segment follow the earlier one's person?

    before, after : (n_overlap, 478, 3) the overlap as each segment tracked it
    rest : (n, 478, 3) the later segment's share
    last : the earlier segment's :func:`_last_face` over its kept frames, its row counted from the
        share's start (negative), or None
    """
    (c0, w0), (c1, _) = _centres(before), _centres(after)
    both = np.flatnonzero(np.isfinite(c0[:, 0]) & np.isfinite(c1[:, 0]))[-5:]
    if len(both):
        distance = np.linalg.norm(c0[both] - c1[both], axis=1)
        return bool(np.median(distance / w0[both]) <= 0.5)
    if last is None:  # the earlier segment never saw a face: the follower starts afresh either way
        return True
    seen = np.flatnonzero(np.isfinite(np.concatenate([after, rest])[:, 0, 0]))
    if not len(seen):
        return True
    row, centre, width = last
    first = int(seen[0]) - len(after)  # counted from the share's start, like ``row``
    centre_1 = _centres(np.concatenate([after, rest])[seen[:1]])[0][0]
    allowed = max_jump * width * (1 + 0.1 * (first - row - 1))
    return bool(np.linalg.norm(centre_1 - centre) <= allowed)


def _seed(last) -> dict:
    """The :class:`~keyshape.capture.FaceFollower` state at the share's start after ``last``."""
    if last is None:
        return {}
    row, centre, width = last
    return {"last": centre, "width": width, "missing": -row - 1}


# --------------------------------------------------------------------------- the whole


def _progress_bar(path: Path, segments: list[Segment], folders: list[Path], progress: bool):
    """A thread showing the frames tracked by all workers (from the size of their files); stop()."""
    from tqdm import tqdm

    stop = threading.Event()
    total = sum(s.end - s.first for s in segments)
    bar = tqdm(total=total, unit="frame", desc=f"track {path.name} ({len(segments)} workers)",
               disable=None if progress else True, leave=False, dynamic_ncols=True)
    frame_bytes = 478 * 3 * 4

    def poll():
        while not stop.wait(0.25):
            done = sum(f.joinpath("points.f32").stat().st_size // frame_bytes
                       for f in folders if f.joinpath("points.f32").exists())
            bar.update(max(0, min(done, total) - bar.n))

    thread = threading.Thread(target=poll, daemon=True, name="keyshape-track-progress")
    thread.start()

    def close():
        stop.set()
        thread.join()
        bar.close()

    return close


def start_workers(n: int) -> list[subprocess.Popen]:
    """``n`` fresh interpreters (:func:`_worker`): each imports MediaPipe and PyAV at once (about
    a second), then waits for its job on stdin (:func:`_send`). End them with :func:`stop_workers`.

    Not multiprocessing: its spawn re-runs the parent's ``__main__`` (the ``keyshape`` command
    itself), and fork would copy MediaPipe's and the decoder's threads."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    return [subprocess.Popen([sys.executable, "-c", "from keyshape.capture._parallel import _worker; _worker()"],
                             stdin=subprocess.PIPE, env=env) for _ in range(n)]


def stop_workers(processes: list[subprocess.Popen]) -> None:
    """End the workers still running: not needed (too short an input), or after an error or Ctrl-C
    (do not wait for the others' segments)."""
    for process in processes:
        if process.poll() is None:
            process.terminate()
            process.wait()
        if process.stdin is not None and not process.stdin.closed:
            with contextlib.suppress(OSError):  # the worker is gone: its pipe is broken
                process.stdin.close()


def _send(process: subprocess.Popen, job: tuple, folder: Path) -> None:
    """Hand ``job`` (``(function, *arguments)``) to a waiting worker; its result goes to ``folder``."""
    try:
        with process.stdin:
            pickle.dump((job, folder / "result.pickle"), process.stdin)
    except OSError:  # the worker died: _collect says so with its exit code
        pass


def _worker() -> None:
    """Entry point of a worker process: the tracker's imports, then a job on stdin, its result (or
    error) pickled to a file.

    Ctrl-C in a terminal reaches the whole process group; the parent ends its workers itself
    (:func:`stop_workers`), so a worker ignores SIGINT instead of printing a traceback of its own.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from .mediapipe import preload

    preload()
    try:
        job, result = pickle.load(sys.stdin.buffer)
    except EOFError:  # not needed after all
        return
    try:
        outcome = ("ok", job[0](*job[1:]))
    except Exception as exc:  # noqa: BLE001 - handed to the parent, which re-raises it
        outcome = ("error", exc)
    partial = result.with_suffix(".partial")
    try:
        partial.write_bytes(pickle.dumps(outcome))
        partial.replace(result)
    except OSError as exc:  # no room even for the result: the parent says so, naming the folder
        partial.unlink(missing_ok=True)
        os._exit(_UNWRITTEN + exc.errno if exc.errno and exc.errno < 256 - _UNWRITTEN else _UNWRITTEN)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)  # the files are written and closed; the interpreter's teardown (0.1-0.2 s) would delay the parent


_UNWRITTEN = 100  # a worker's exit code when it could not write its result: 100 + the write's errno


def _collect(process: subprocess.Popen, folder: Path, segment: Segment) -> dict:
    code = process.wait()
    result = folder / "result.pickle"
    if not result.exists() and _UNWRITTEN <= code < 256:
        why = os.strerror(code - _UNWRITTEN) if code > _UNWRITTEN else "an error"
        raise WriteError(f"{folder}: cannot write the tracking of frames {segment.first}..{segment.end - 1} ({why})")
    if not result.exists():
        raise RuntimeError(f"the worker tracking frames {segment.first}..{segment.end - 1} exited with code {code}")
    kind, value = pickle.loads(result.read_bytes())
    if kind == "error":
        raise value
    return value


def _track_all(track_segment, spool_type, path, info, segments, folders, pts, kwargs, progress,
               processes: list[subprocess.Popen]) -> list:
    """Every segment: the first in this process, the others in the waiting worker ``processes``."""
    jobs = [(track_segment, path, info, s.first, s.end, f, pts, kwargs) for s, f in zip(segments, folders)]
    for process, job, f in zip(processes, jobs[1:], folders[1:]):
        _send(process, job, f)
    close = _progress_bar(path, segments, folders, progress)
    try:
        states = [track_segment(*jobs[0][1:])]
        states += [_collect(p, f, s) for p, f, s in zip(processes, folders[1:], segments[1:])]
    finally:
        close()
        stop_workers(processes)
    return [_rebuilt(spool_type, f, state) for f, state in zip(folders, states)]


def _stitch(track_segment, spool_type, path, info, segments, spools, pts, kwargs, folder: Path) -> list:
    """(spool, first row kept) per segment, re-tracking a share that followed someone else."""
    kept = [(spools[0], 0)]
    for k in range(1, len(segments)):
        segment, spool = segments[k], spools[k]
        before_spool, before_row = kept[-1]
        before = before_spool.arrays()["points"]
        warm = segment.share - segment.first
        after = spool.arrays()["points"]
        last = _last_face(before[before_row:])
        if last is not None:
            last = (last[0] + before_row - len(before), *last[1:])
        if _same_person(before[len(before) - warm:], after[:warm], after[warm:], last):
            kept.append((spool, warm))
            continue
        again = folder / f"segment{k}-again"
        again.mkdir()
        state = track_segment(path, info, segment.share, segment.end, again, pts, kwargs, _seed(last))
        kept.append((_rebuilt(spool_type, again, state), 0))
    return kept


def _carry_hands(path: Path, fps: float | None, pts: np.ndarray | None, kept: list) -> None:
    """Hands that cross a segment's first frame, followed on into it as one process would.

    MediaPipe's hand landmarker finds a hand over a face mostly by following it from where it came
    into the picture (its palm detector seldom finds a hand already lying on a face), so a segment
    that starts while a hand is over the face would miss it. Where the kept rows before a segment
    end with a hand, its frames are looked at again from the frame that hand run began in (no
    hand before it: a landmarker in the state a fresh one has), and the segment's hands rows
    rewritten, until the new pass and the segment's own say no hand in the same frame (from there
    on they agree). kept : (spool, first row kept) per segment, as :func:`_stitch` gives them.
    """
    from .mediapipe import HandTracker
    from .video import iter_frames

    for k in range(1, len(kept)):
        (before, before_row), (spool, row) = kept[k - 1], kept[k]
        hands_before = before.arrays()["hands"]
        if not len(hands_before) or not np.isfinite(hands_before[-1, :, 0, 0]).any():
            continue
        entry = len(hands_before) - 1
        while entry > before_row and np.isfinite(hands_before[entry - 1, :, 0, 0]).any():
            entry -= 1
        first = before.index[entry]
        points, own = spool.arrays()["points"], spool.arrays()["hands"]
        points_before = before.arrays()["points"]
        boundary = spool.index[row]
        with HandTracker() as tracker, open(spool.folder / "hands.f32", "r+b") as out:
            for at, (ms, rgb) in enumerate(iter_frames(path, start=first, fps=fps, pts=pts), start=first):
                r = row + at - boundary  # the segment's row of this frame (< row: the segment before's)
                if r >= len(points):
                    break
                face = points_before[entry + at - first] if r < row else points[r]
                hands = tracker.detect(rgb, ms, face) if np.isfinite(face[0, 0]) else \
                    np.full(own.shape[1:], np.nan, np.float32)
                if r < row:
                    continue  # frames of the segment before: the same as it found
                found, had = bool(np.isfinite(hands[:, 0, 0]).any()), bool(np.isfinite(own[r, :, 0, 0]).any())
                if not found and not had:
                    break
                out.seek(r * hands.nbytes)
                out.write(np.ascontiguousarray(hands, dtype=np.float32).tobytes())
                spool.n_hands += int(found) - int(had)


def _join(spool_type, kept: list, folder: Path):
    """One spool in ``folder`` holding the kept rows of every segment, in order."""
    with spool_type(folder) as joined:
        for spool, row in kept:
            arrays = spool.arrays()
            for lo in range(row, spool.n_frames, _CHUNK):
                for name, fh in joined.files.items():
                    fh.write(np.ascontiguousarray(arrays[name][lo:lo + _CHUNK]).tobytes())
            joined.n_frames += spool.n_frames - row
            joined.n_faces += int(np.isfinite(arrays["points"][row:, 0, 0]).sum())
            joined.n_hands += int(np.isfinite(arrays["hands"][row:, :, 0, 0]).any(axis=1).sum())
            joined.most_seen = max(joined.most_seen, spool.most_seen)
            joined.index += spool.index[row:]
            joined.ms += spool.ms[row:]
            del arrays
    return joined


def spool_parallel(path: Path, info: VideoInfo, track_segment, spool_type, *, start: int, end: int | None,
                   progress: bool, folder: Path, processes: list[subprocess.Popen], **kwargs):
    """Track ``start <= i < end`` in parallel segments into a spool in ``folder``; None when the
    input is too short to split (or its length unknown): track it in one process then.

    track_segment : ``keyshape.capture._track._track_segment``, run in every worker
    spool_type : ``keyshape.capture._spool.Spool``
    processes : :func:`start_workers`, one per segment after the first (this process tracks that
        one); the caller stops those not needed (:func:`stop_workers`)
    kwargs : the tracker's settings (``options``, ``fps``, ``face``, ``one_euro``, ``hands``)
    """
    workers = len(processes) + 1
    stop = min(end, info.n_frames) if end is not None and info.n_frames else info.n_frames
    overlap = max(MIN_OVERLAP, round(OVERLAP_SECONDS * info.fps))
    segments = plan_segments(start, stop, workers, overlap) if stop > start else []
    if len(segments) < 2:
        return None
    pts = frame_pts(path)
    if pts is not None and len(pts) != info.n_frames:  # frame numbers from times would not match
        pts = None
    folders = [folder / f"segment{k}" for k in range(len(segments))]
    for f in folders:
        f.mkdir()
    spools = _track_all(track_segment, spool_type, path, info, segments, folders, pts, kwargs, progress, processes)
    if any(spool.n_frames != s.end - s.first for spool, s in zip(spools, segments)):
        return None  # the video is shorter than it declares: one process finds where it ends
    kept = _stitch(track_segment, spool_type, path, info, segments, spools, pts, kwargs, folder)
    if kwargs.get("hands"):
        _carry_hands(path, kwargs.get("fps"), pts, kept)
    return _join(spool_type, kept, folder)
