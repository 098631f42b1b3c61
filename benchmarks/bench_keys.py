"""Benchmark key selection (``keyshape keys``) against the number of frames.

Peak memory (tracemalloc) and wall time of :func:`keyshape.keyshapes._search.find_keyshapes`
(``spa``, K = 12 per region, weights bounded by 1, both regions of the ``upper-lower``
scheme) on synthetic MediaPipe-like takes of 478 landmarks in 3D, and the RMS
reconstruction error of the keys it returns over every frame (% of the inter-ocular
distance), so the quality of the bounded search on long takes can be compared.

Paths measured, each size in a fresh process:

``pool``
    the current code: every frame is a candidate up to ``MAX_CANDIDATES`` (2048), beyond
    that the keys are searched among a pool of 2048 frames (:func:`keyshape.keyshapes._select.pool`);
``all``
    the current code with no pool (``MAX_CANDIDATES`` raised above the number of frames):
    the frames × frames search, which picks the same keys as before the pool existed;
``old``
    the source tree of a git revision (``--old-rev``), e.g. the commit before the pool and
    the smaller temporaries, run as it was.

The quadratic paths run only up to ``--max-quadratic`` frames (default 8,000: about
2.5 GB for ``old``); beyond it they would need tens of GB.

Run::

    python benchmarks/bench_keys.py                       # 2k, 8k, 32k, 100k frames
    python benchmarks/bench_keys.py --old-rev 30e7e52     # also the old source tree
    python benchmarks/bench_keys.py --quick               # 1k and 4k frames, a smoke test
    python benchmarks/bench_keys.py --json out.json       # also write the numbers

The synthetic take: a random face (478 points on a half ellipsoid, face-sized), 16 random
key deltas per region on its landmarks, smooth sparse non-negative weights (each key
active about 16 % of the time, a region's weights summing to at most 0.9), one frame per
key at weight 1 alone, a neutral frame, Gaussian noise of 0.15 units: a take that K = 12
keys per region explain only approximately, as real ones. The same generator, seed and
statistics at every length. OpenBLAS runs single-threaded unless ``OPENBLAS_NUM_THREADS``
is set.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads OpenBLAS

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d

N_LANDMARKS = 478
N_TRUE = 16  # key deltas per region in the synthetic rig
K = 12  # keys selected per region
SIZES = (2_000, 8_000, 32_000, 100_000)
QUICK_SIZES = (1_000, 4_000)
REPO = Path(__file__).resolve().parents[1]
BYTES_PER_FRAME_PAIR = {"all": 19, "old": 42}  # measured peaks of the quadratic paths, for skipped sizes


# --------------------------------------------------------------------------- synthetic data


def synthetic_take(n_frames: int, seed: int = 0, noise: float = 0.15):
    """``(track, regions, neutral_frame)``: a MediaPipe-like aligned take (see the module notes)."""
    from keyshape.containers import Track
    from keyshape.schemes import resolve_regions

    rng = np.random.default_rng(seed)
    theta = rng.uniform(0, 2 * np.pi, N_LANDMARKS)
    radius = np.sqrt(rng.uniform(0.05, 1.0, N_LANDMARKS))
    neutral = np.stack([60 * radius * np.cos(theta), 80 * radius * np.sin(theta),
                        -40 * np.sqrt(np.clip(1 - radius**2, 0, None))], axis=1)
    regions = resolve_regions("upper-lower", N_LANDMARKS)
    deltas = np.zeros((N_TRUE * len(regions), N_LANDMARKS, 3))
    for r, landmarks in enumerate(regions.values()):
        deltas[r * N_TRUE:(r + 1) * N_TRUE, landmarks] = 4.0 * rng.standard_normal((N_TRUE, len(landmarks), 3))
    n_keys = len(deltas)
    raw = gaussian_filter1d(rng.standard_normal((n_frames, n_keys)), sigma=4, axis=0)
    weights = np.clip(raw / raw.std(axis=0) - 1.0, 0, None)
    weights /= weights.max(axis=0)
    for r in range(len(regions)):
        cols = slice(r * N_TRUE, (r + 1) * N_TRUE)
        weights[:, cols] *= 0.9 / np.maximum(weights[:, cols].sum(axis=1, keepdims=True), 0.9)
    planted = rng.choice(n_frames, n_keys + 1, replace=False)
    weights[planted[:-1]], weights[planted[-1]] = np.eye(n_keys), 0.0
    points = np.empty((n_frames, N_LANDMARKS, 3))
    flat, block = points.reshape(n_frames, -1), 8192
    for start in range(0, n_frames, block):  # no second take-sized array
        stop = min(start + block, n_frames)
        flat[start:stop] = weights[start:stop] @ deltas.reshape(n_keys, -1)
        flat[start:stop] += neutral.ravel() + noise * rng.standard_normal((stop - start, flat.shape[1]))
    return Track(points, 30.0), regions, int(planted[-1])


# --------------------------------------------------------------------------- one measurement


def measure(n_frames: int, path: str) -> dict:
    """Select the keys of one synthetic take; peak traced memory, wall time and RMS errors."""
    from keyshape.keyshapes import _search as keyshapes
    from keyshape.metrics import face_scale

    track, regions, neutral = synthetic_take(n_frames)
    if path == "all":
        keyshapes.MAX_CANDIDATES = n_frames + 1
    tracemalloc.start()
    start = time.perf_counter()
    keys = keyshapes.find_keyshapes(track, regions=regions, n_keys=K, neutral_frame=neutral, upper=1.0)
    wall = time.perf_counter() - start
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    candidates = np.flatnonzero(track.valid)
    candidates = candidates[candidates != neutral]
    scale, _ = face_scale(track.points[neutral])
    rms = {}
    for region, landmarks in regions.items():  # over every frame, outside the measurement
        data = (track.points[np.ix_(candidates, landmarks)] - track.points[neutral, landmarks]).reshape(
            candidates.size, -1)
        rows = np.searchsorted(candidates, keys.frames[keys.keys_of(region)])
        squared = squared_error(data, rows, upper=1.0)
        rms[region] = 100 * np.sqrt(squared / ((candidates.size + 1) * len(landmarks))) / scale
    return {"frames": n_frames, "path": path, "peak_mib": peak / 2**20, "wall_s": wall,
            "rms_upper": rms["upper"], "rms_lower": rms["lower"], "key_frames": keys.frames.tolist()}


def squared_error(X: np.ndarray, rows: np.ndarray, *, upper: float, block: int = 8192) -> float:
    """``Σ_f min_{0 <= w <= upper} |x_f − w X[rows]|²`` over every row of ``X``, by blocks (any
    keyshape version: only :func:`keyshape.decompose._solve.solve_nnls`)."""
    from keyshape.decompose import solve_nnls

    basis, total = X[rows], 0.0
    for start in range(0, len(X), block):
        chunk = X[start:start + block]
        total += float(((chunk - solve_nnls(basis.T, chunk, upper=upper) @ basis) ** 2).sum())
    return total


def run(n_frames: int, path: str, old_src: Path | None) -> dict:
    """:func:`measure` in a fresh process (``old``: with the old source tree first on the path)."""
    env = dict(os.environ)
    if path == "old":
        env["PYTHONPATH"] = os.pathsep.join([str(old_src), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    command = [sys.executable, __file__, "--worker", str(n_frames), "old" if path == "old" else path]
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
    if done.returncode:
        raise RuntimeError(f"{path} at {n_frames} frames failed:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def old_tree(rev: str, into: Path) -> Path:
    """Extract ``src/keyshape`` of ``rev`` into ``into``; the directory to put on PYTHONPATH."""
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev, "src/keyshape"], capture_output=True,
                             check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into / "src"


# --------------------------------------------------------------------------- report


def machine() -> str:
    memory = ""
    try:
        with open("/proc/meminfo") as f:
            memory = f", {int(f.readline().split()[1]) / 2**20:.0f} GiB"
    except OSError:
        pass
    return (f"{platform.machine()}, {os.cpu_count()} cores{memory}, Python {platform.python_version()}, "
            f"numpy {np.__version__}, OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}, "
            f"load average {os.getloadavg()[0]:.1f}")


def table(results: list[dict]) -> str:
    """Markdown rows; "same keys" compares each path's key frames with those of ``all`` (same size)."""
    every = {r["frames"]: r["key_frames"] for r in results if r["path"] == "all" and "key_frames" in r}
    head = "| frames | path | peak memory (MiB) | wall time (s) | RMS error upper / lower (% IOD) | same keys as all |"
    lines = [head, "|---:|---|---:|---:|---|---|"]
    for r in results:
        if "skipped" in r:
            lines.append(f"| {r['frames']:,} | {r['path']} | {r['skipped']} | | | |")
            continue
        same = "" if r["path"] == "all" or r["frames"] not in every else (
            "yes" if r["key_frames"] == every[r["frames"]] else "no")
        lines.append(f"| {r['frames']:,} | {r['path']} | {r['peak_mib']:.0f} | {r['wall_s']:.1f} | "
                     f"{r['rms_upper']:.3f} / {r['rms_lower']:.3f} | {same} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help=f"frames (default {SIZES})")
    parser.add_argument("--quick", action="store_true", help=f"sizes {QUICK_SIZES}")
    parser.add_argument("--old-rev", default=None, help="also run this git revision's source tree (path old)")
    parser.add_argument("--max-quadratic", type=int, default=8_000,
                        help="largest take the frames x frames paths run on (default 8000)")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    parser.add_argument("--worker", nargs=2, metavar=("FRAMES", "PATH"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        print(json.dumps(measure(int(args.worker[0]), args.worker[1])))
        return 0
    sizes = args.sizes or (QUICK_SIZES if args.quick else SIZES)
    paths = ["pool", "all"] + (["old"] if args.old_rev else [])
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        old_src = old_tree(args.old_rev, Path(tmp)) if args.old_rev else None
        for n in sizes:
            for path in paths:
                if path != "pool" and n > args.max_quadratic:
                    need = n**2 * BYTES_PER_FRAME_PAIR[path] / 2**30
                    results.append({"frames": n, "path": path, "skipped": f"not run (≈ {need:,.0f} GiB)"})
                    continue
                results.append(run(n, path, old_src))
                r = results[-1]
                print(f"{n:>7} frames  {path:<5} peak {r['peak_mib']:8.1f} MiB  {r['wall_s']:7.1f} s  "
                      f"RMS {r['rms_upper']:.3f} / {r['rms_lower']:.3f}", file=sys.stderr, flush=True)
    print(f"Machine: {machine()}\n")
    print(table(results))
    if args.json:
        args.json.write_text(json.dumps({"machine": machine(), "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
