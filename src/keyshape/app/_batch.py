"""Many takes at once: ``keyshape batch``, on local cores or a Ray cluster, resumable.

Every take goes to ``OUTDIR/<take stem>/`` exactly as ``keyshape run`` would write it
(:func:`keyshape.app._run.run_take`, staged and moved in only on success). A take whose
``take.json`` and the files it lists already exist is skipped; a take that fails is reported
with its one-line error and the others go on. With a shared key set, every take is tracked
first, one key set is discovered across all of them (``OUTDIR/keys.json``) and every take is
solved against it, without tracking it again.

The work runs on Ray when it is installed (:mod:`keyshape.app._ray`), otherwise - or with
``sequential=True`` - in this process, one take after the other, with the same outputs.

Resume is decided by a manifest: each finished take's folder holds ``batch.json``, the
fingerprint (SHA-256) of its video and the options it was made with (with the fingerprints of the
rig, mapping and key files they name). A rerun skips a take only when its outputs are complete
and its manifest matches the video and options of this run; a replaced video or a changed option
(``--count 3``) makes it run again, and ``force=True`` (``--force``) reruns every take.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Self

from ..exceptions import InputError, KeyshapeError
from ..io.atomic import new_folders, remove_dead_stages
from ._run import RunOptions

__all__ = ["VIDEO_SUFFIXES", "BatchRow", "batch", "find_takes", "format_table", "is_complete", "take_folder"]

VIDEO_SUFFIXES = frozenset({".mp4", ".mov", ".m4v", ".mkv", ".avi", ".webm", ".mpg", ".mpeg", ".wmv"})
SUMMARY_FIELDS = ("take", "frames", "detection_rate", "keys", "error_pct", "status", "seconds", "error")
TRACKS = ".tracks"  # OUTDIR/.tracks/<stem>.npz: tracks of the shared-keys pass, kept until solved
MANIFEST = "batch.json"  # OUTDIR/<stem>/batch.json: what the finished take was made from


@dataclass(frozen=True)
class BatchRow:
    """One take's line of the summary: status is "ok", "skipped" or "failed"."""

    take: str
    frames: int | None = None
    detection_rate: float | None = None
    keys: int | None = None  # key shapes over all regions
    error_pct: float | None = None
    status: str = "ok"
    seconds: float = 0.0
    error: str = ""

    def as_csv(self) -> dict:
        def num(value, fmt):
            return "" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, fmt)

        return {"take": self.take, "frames": num(self.frames, "d"),
                "detection_rate": num(self.detection_rate, ".4f"), "keys": num(self.keys, "d"),
                "error_pct": num(self.error_pct, ".3f"), "status": self.status,
                "seconds": f"{self.seconds:.1f}", "error": self.error}


# -- finding the takes ---------------------------------------------------------------------------

def find_takes(paths: Sequence[str | Path]) -> list[Path]:
    """The videos named by ``paths``: files as given, folders as the videos directly inside them.

    A folder's hidden files are left out (as ``ls`` leaves them out); every take's folder name is
    :func:`take_folder`'s. Raises InputError for a missing path, a folder without videos, a video
    whose name gives no take folder, or two takes with the same stem (they would share an output
    folder).
    """
    takes: list[Path] = []
    for path in map(Path, paths):
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES
                           and not p.name.startswith("."))
            if not found:
                raise InputError(f"{path}: no videos in this folder ({', '.join(sorted(VIDEO_SUFFIXES))})")
            takes.extend(found)
        elif path.is_file():
            takes.append(path)
        else:
            raise InputError(f"{path}: no such file or folder")
    return _check_stems(takes)


_OWN_NAMES = frozenset({"summary.csv", "keys.json", TRACKS})  # what batch itself writes in OUTDIR


def take_folder(video: str | Path) -> str:
    """The name of ``video``'s take folder in OUTDIR: its stem, the one rule every take follows.

    Raises InputError naming the video when the stem is no plain folder name: empty, ``.`` or
    ``..`` (the folder would be OUTDIR itself or its parent), hidden (keyshape's stage and cache
    folders are), or one of the files batch writes in OUTDIR (``summary.csv``, ``keys.json``).

    Examples
    --------
    >>> take_folder("takes/actor 1.mp4")
    'actor 1'
    """
    stem = Path(video).stem
    problem = ("the folder would be OUTDIR or its parent" if stem in ("", ".", "..") else
               "a hidden folder" if stem.startswith(".") else
               "a name batch writes itself" if stem in _OWN_NAMES else None)
    if problem is not None:
        raise InputError(f"{video}: its name gives no take folder ({stem!r}: {problem}); rename the video")
    return stem


def _check_stems(takes: list[Path]) -> list[Path]:
    seen: dict[str, Path] = {}
    for take in takes:
        name = take_folder(take)
        if name in seen and seen[name].resolve() != take.resolve():
            raise InputError(f"two takes would share the output folder {name!r}: "
                             f"{seen[name]} and {take}; rename one")
        seen.setdefault(name, take)
    return list(seen.values())


def is_complete(folder: str | Path) -> bool:
    """Whether ``folder`` holds a finished take: ``take.json`` and every file it lists, and no
    trace of a switch cut short (:data:`keyshape.io.atomic.SWITCH`)."""
    from ..io.atomic import SWITCH

    folder = Path(folder)
    if (folder / SWITCH).exists():
        return False
    try:
        info = json.loads((folder / "take.json").read_text())
    except (OSError, ValueError):
        return False
    files = info.get("files") if isinstance(info, dict) else None
    return isinstance(files, dict) and all((folder / str(name)).is_file() for name in files.values())


# -- the manifest: what a finished take was made from -----------------------------------------------

def fingerprint(path: str | Path) -> str:
    """SHA-256 of a file's bytes, or of a folder's file names and bytes (an OBJ rig folder)."""
    path = Path(path)
    digest = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for file in files:
        digest.update(str(file.relative_to(path) if path.is_dir() else "").encode() + b"\0")
        with open(file, "rb") as fh:
            while chunk := fh.read(1 << 20):
                digest.update(chunk)
    return digest.hexdigest()


def take_manifest(video: Path, options: RunOptions) -> dict:
    """The video's fingerprint and every option, files among them by fingerprint (JSON-ready)."""
    def plain(value):
        if isinstance(value, Path):
            return {"path": str(value), "sha256": fingerprint(value) if value.exists() else None}
        if isinstance(value, dict):
            return {str(k): plain(v) for k, v in sorted(value.items())}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return value

    return {"format": "keyshape-batch-take", "version": 1, "video": str(Path(video).resolve()),
            "sha256": fingerprint(video),
            "options": {f.name: plain(getattr(options, f.name)) for f in dataclasses.fields(options)}}


def _is_current(folder: Path, video: Path, options: RunOptions) -> bool:
    """Whether ``folder`` holds a finished take made from this video with these options."""
    if not is_complete(folder):
        return False
    try:
        made = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError):
        return False
    if not isinstance(made, dict) or not isinstance(made.get("outputs"), dict):
        return False
    outputs = made.pop("outputs")
    return made == take_manifest(video, options) and outputs == _output_digests(folder)


def _output_digests(folder: Path) -> dict[str, str]:
    """SHA-256 of every file the take's run wrote (its ``take.json`` says which, itself included): a
    take whose output was changed since (a keys.json overwritten, a weights.csv edited) is made
    again, not skipped. The user's own files in the folder do not count."""
    from ..io.take import written_by

    names = sorted(written_by(folder) | {"take.json"})
    return {name: fingerprint(folder / name) if (folder / name).is_file() else None for name in names}


def _write_manifest(folder: Path, manifest: dict) -> None:
    from ..io.atomic import atomic_path

    with atomic_path(folder / MANIFEST) as tmp:
        tmp.write_text(json.dumps(manifest, indent=1) + "\n")


# -- the work of one take (runs in a worker) ------------------------------------------------------

def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or exc.__class__.__name__
    return text if isinstance(exc, KeyshapeError) else f"{exc.__class__.__name__}: {text}"


def _row(summary) -> BatchRow:
    return BatchRow(summary.take, summary.n_frames, summary.detection_rate,
                    sum(summary.keys_per_region.values()), summary.error_pct, "ok", summary.seconds)


def _guarded(name: str, work: Callable[[], BatchRow]) -> BatchRow:
    """Run ``work``; any error becomes a failed row with its one-line message."""
    start = time.perf_counter()
    try:
        return work()
    except Exception as exc:  # noqa: BLE001 - one take's failure must not stop the batch
        return BatchRow(name, status="failed", seconds=time.perf_counter() - start, error=_one_line(exc))


def _run_task(job: tuple[Path, Path, RunOptions, Path | None]) -> BatchRow:
    """Worker: one take start to finish (from its cached track when there is one)."""
    video, outdir, options, track_path = job

    def work() -> BatchRow:
        manifest = take_manifest(video, options)  # before the work: the inputs it starts from
        if track_path is None:
            from ._run import run_take

            row = _row(run_take(video, outdir, options, progress=False))
        else:
            row = _row(_run_tracked(video, outdir, options, track_path))
        _write_manifest(outdir, {**manifest, "outputs": _output_digests(outdir)})
        return row

    return _guarded(video.name, work)


def _track_task(job: tuple[Path, Path, dict]) -> BatchRow:
    """Worker: track one take into ``track_path`` (the shared-keys pass)."""
    video, track_path, capture = job

    def work() -> BatchRow:
        from ..capture import track_video
        from ..io.track import save_track

        start = time.perf_counter()
        track = track_video(video, progress=False, **capture)
        save_track(track, track_path)
        return BatchRow(video.name, track.n_frames, float(track.valid.mean()), status="tracked",
                        seconds=time.perf_counter() - start)

    return _guarded(video.name, work)


def _run_tracked(video: Path, outdir: Path, options: RunOptions, track_path: Path):
    """:func:`keyshape.app._run.run_take` on a track already made (the shared-keys pass)."""
    from ..io.track import load_track
    from ._run import run_take

    return run_take(video, outdir, options, progress=False, track=load_track(track_path))


# -- runners --------------------------------------------------------------------------------------

class SequentialRunner:
    """The runner without Ray: every task in this process, in order."""

    name = "sequential"
    n_workers = 1

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        pass

    def map(self, fn: Callable, items: Iterable) -> Iterator[tuple[object, object]]:
        for item in items:
            yield item, fn(item)


def make_runner(*, sequential: bool = False, workers: int | None = None, address: str | None = None):
    """Ray when asked for or available, else the sequential runner.

    ``address`` without Ray installed raises MissingDependencyError (it cannot be honoured).
    """
    from ._ray import RayRunner, ray_available

    if sequential:
        if address is not None:
            raise InputError("--sequential and --address exclude each other")
        return SequentialRunner()
    if address is None and not ray_available():
        return SequentialRunner()
    return RayRunner(workers=workers, address=address)


# -- the batch ------------------------------------------------------------------------------------

def batch(takes: Sequence[str | Path], outdir: str | Path, options: RunOptions | None = None, *,
          shared_keys: bool = False, runner=None, on_row: Callable[[BatchRow], None] | None = None,
          force: bool = False) -> list[BatchRow]:
    """Process every take into ``outdir/<stem>/``; return one row per take, in input order.

    Parameters
    ----------
    takes : video files and/or folders of videos (see :func:`find_takes`)
    outdir : output folder; ``summary.csv`` is written there (atomically), and with
        ``shared_keys`` the common key set ``keys.json``
    options : RunOptions of every take; ``options.keys`` reuses one key set for all
    shared_keys : discover one key set across all takes, then solve every take against it
    runner : :func:`make_runner`'s result (default: Ray if installed, else sequential)
    on_row : called with each take's row as it finishes (for progress lines)
    force : rerun every take, even those whose manifest matches (and track the shared-keys takes
        again, and discover their key set again)
    """
    videos, outdir = find_takes(takes), Path(outdir)
    options = options if options is not None else RunOptions()
    if shared_keys and options.keys is not None:
        raise InputError("--keys and --shared-keys exclude each other: give one key set or discover one")
    with new_folders(outdir):  # stopped before any take is in: no empty OUTDIR is left
        return _batch(videos, outdir, options, shared_keys, runner, on_row, force)


def _batch(videos: list[Path], outdir: Path, options: RunOptions, shared_keys: bool, runner, on_row,
           force: bool) -> list[BatchRow]:
    remove_dead_stages(outdir)  # the stages of takes an earlier batch was stopped in (killed workers)
    if force and shared_keys:
        _forget_shared(outdir)
    made_with = replace(options, keys=outdir / "keys.json") if shared_keys else options
    rows = {} if force else {v: _skipped_row(v, outdir) for v in videos
                             if _is_current(outdir / take_folder(v), v, made_with)}
    pending = [v for v in videos if v not in rows]
    report = on_row or (lambda row: None)
    for row in rows.values():
        report(row)
    if pending:  # a finished batch does not start Ray
        try:
            with runner if runner is not None else make_runner() as active:
                rows.update(_process(pending, outdir, options, shared_keys, active, report))
        finally:  # stopped: what its killed workers staged goes now (or on the next batch)
            remove_dead_stages(outdir)
    ordered = [rows[v] for v in videos]
    write_summary(ordered, outdir / "summary.csv")
    return ordered


def _process(videos: list[Path], outdir: Path, options: RunOptions, shared_keys: bool, runner,
             report) -> dict[Path, BatchRow]:
    rows: dict[Path, BatchRow] = {}
    tracks: dict[Path, Path] = {}
    if shared_keys:
        options, tracks, failed = _shared_key_set(videos, outdir, options, runner)
        for video, row in failed.items():
            rows[video] = row
            report(row)
    jobs = [(v, outdir / take_folder(v), options, tracks.get(v)) for v in videos if v not in rows]
    for job, row in runner.map(_run_task, jobs):
        rows[job[0]] = row if isinstance(row, BatchRow) else _crashed(job[0], row)
        report(rows[job[0]])
        if rows[job[0]].status == "ok" and job[3] is not None:
            job[3].unlink(missing_ok=True)
    if tracks and not any((outdir / TRACKS).iterdir()):
        (outdir / TRACKS).rmdir()
    return rows


def _forget_shared(outdir: Path) -> None:
    """``--force --shared-keys``: the cached tracks and the key set are made again."""
    import shutil

    shutil.rmtree(outdir / TRACKS, ignore_errors=True)
    (outdir / "keys.json").unlink(missing_ok=True)


def _crashed(video: Path, exc: BaseException) -> BatchRow:
    return BatchRow(video.name, status="failed", error=f"worker lost: {_one_line(exc)}")


def _shared_key_set(videos: list[Path], outdir: Path, options: RunOptions, runner
                    ) -> tuple[RunOptions, dict[Path, Path], dict[Path, BatchRow]]:
    """Track the takes (reusing tracks kept from an interrupted run), then find or reuse
    ``outdir/keys.json``. Returns the options with that key set, the track of each take and
    the rows of the takes that failed."""
    from ..io.keys_json import load_keys, save_keys
    from ..io.track import load_track
    from ._pipeline import discover_keys

    cache = outdir / TRACKS
    cache.mkdir(exist_ok=True)
    tracks = {v: cache / f"{take_folder(v)}.npz" for v in videos}
    jobs = [(v, tracks[v], options.capture) for v in videos if not tracks[v].is_file()]
    failed = {}
    for job, row in runner.map(_track_task, jobs):
        if not isinstance(row, BatchRow) or row.status == "failed":
            failed[job[0]] = row if isinstance(row, BatchRow) else _crashed(job[0], row)
    keys_path = outdir / "keys.json"
    loaded = {v: load_track(tracks[v]) for v in videos if v not in failed}  # read once, for both below
    if not keys_path.is_file():  # a rerun keeps the key set its finished takes were solved with
        if not loaded:
            return replace(options, keys=keys_path), tracks, failed
        keys = discover_keys(list(loaded.values()), regions=options.regions,
                             n_keys=options.n_keys, method=options.method, neutral=options.neutral,
                             take=[v.name for v in loaded], upper=options.upper, max_error=options.max_error,
                             mirror=options.mirror)
        save_keys(keys, keys_path)
    else:
        keys = load_keys(keys_path)
    _warn_out_of_reach(keys, keys_path, loaded, options)
    return replace(options, keys=keys_path), tracks, failed


def _warn_out_of_reach(keys, keys_path: Path, tracks: dict, options: RunOptions) -> None:
    """Warn about every take (``tracks``: video -> Track) the shared key set does not reach within
    the error target (a take added after the key set was made, or one unlike the others)."""
    import shlex
    import warnings

    from ..exceptions import InputWarning
    from ._pipeline import fit_errors

    for video, track in tracks.items():
        errors, unit = fit_errors(track, keys, upper=options.upper)
        beyond = {r: e for r, e in errors.items() if e > options.max_error}
        if beyond:
            worst = ", ".join(f"{r} {e:.2f}" for r, e in beyond.items())
            saved = shlex.quote(str(keys_path.parent / take_folder(video) / "track.npz"))
            warnings.warn(f"{video.name}: outside the shared key set's reach (RMS error {worst} {unit}, target "
                          f"{options.max_error:g}); `keyshape coverage {saved} --keys {shlex.quote(str(keys_path))}"
                          f" -o DIR` shows where, `keyshape keys {saved} --extend ... -o KEYS.json` adds keys for it",
                          InputWarning, stacklevel=2)


def _skipped_row(video: Path, outdir: Path) -> BatchRow:
    """The row of a finished take: its numbers from the last summary when it has them."""
    previous = _previous_rows(outdir / "summary.csv").get(video.name)
    if previous is not None and previous.status in ("ok", "skipped"):
        return replace(previous, status="skipped", seconds=0.0)
    try:
        frames = int(json.loads((outdir / take_folder(video) / "take.json").read_text())["n_frames"])
    except (OSError, ValueError, KeyError, TypeError):
        frames = None
    return BatchRow(video.name, frames, status="skipped")


def _previous_rows(path: Path) -> dict[str, BatchRow]:
    if not path.is_file():
        return {}

    def opt(text, kind):
        return kind(text) if text not in ("", None) else None

    try:
        with path.open(newline="") as f:
            return {r["take"]: BatchRow(r["take"], opt(r["frames"], int), opt(r["detection_rate"], float),
                                        opt(r["keys"], int), opt(r["error_pct"], float), r["status"])
                    for r in csv.DictReader(f)}
    except (OSError, ValueError, KeyError):
        return {}


# -- the summary ----------------------------------------------------------------------------------

def write_summary(rows: Sequence[BatchRow], path: str | Path) -> Path:
    """Write the summary table as CSV (header :data:`SUMMARY_FIELDS`), atomically."""
    from ..io.atomic import atomic_path

    with atomic_path(path) as tmp, tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=SUMMARY_FIELDS)
        writer.writeheader()
        writer.writerows(row.as_csv() for row in rows)
    return Path(path)


def format_table(rows: Sequence[BatchRow]) -> str:
    """The summary as an aligned text table, failed takes' errors below it."""
    head = ("take", "frames", "face %", "K", "error %", "status", "seconds")
    body = [(r.take, _fmt(r.frames, "d"), _fmt(None if r.detection_rate is None else 100 * r.detection_rate, ".1f"),
             _fmt(r.keys, "d"), _fmt(r.error_pct, ".2f"), r.status, f"{r.seconds:.1f}") for r in rows]
    widths = [max(len(str(line[i])) for line in [head, *body]) for i in range(len(head))]
    lines = ["  ".join(str(c).ljust(w) if i == 0 else str(c).rjust(w) for i, (c, w) in enumerate(zip(line, widths)))
             for line in [head, *body]]
    lines += [f"{r.take}: {r.error}" for r in rows if r.status == "failed"]
    return "\n".join(lines)


def _fmt(value, fmt) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return format(value, fmt)
