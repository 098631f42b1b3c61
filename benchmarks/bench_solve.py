"""``keyshape solve`` on a long take against the naive script, both as whole processes.

    python benchmarks/bench_solve.py                  # 100,000 frames, best of 3
    python benchmarks/bench_solve.py --frames 20000 --repeats 1 --profile

The take is the embedded clip's track (tracked once, here) tiled to ``--frames`` frames with a
little noise (0.3 px), so no two frames are equal; the key set is ``keyshape keys`` on the clip.
The naive script is what one writes first with numpy and scipy (below, :data:`NAIVE`): load the
track and keys, align every frame by Umeyama (one SVD per frame), solve every frame and region
with ``scipy.optimize.nnls``, write the CSV with the ``csv`` module. ``keyshape solve`` runs with
its defaults: the smoothed, bounded solve (``--smooth 0.1 --max 1``), which does more than the
naive per-frame NNLS; ``--smooth 0`` (the per-frame bounded NNLS) is timed too, and (where
``taskset`` exists) the default pinned to one core, as the naive script runs: ``keyshape solve``
solves the regions of a long take on a thread per core. Each command runs as a fresh process
(imports included), alternated, best of ``--repeats`` (wall time, and CPU time, which a shared
machine's load disturbs less), each with its track file read through just before (:func:`warm`).
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path

CLIP = Path(str(resources.files("keyshape").joinpath("data/WolfgangLanger_Pexels.mp4")))

NAIVE = r'''
import csv, json, sys
import numpy as np
from scipy.optimize import nnls

track_path, keys_path, out_path = sys.argv[1:4]
data = np.load(track_path)
points, frame_index, times = data["points"], data["frame_index"], data["time"]
keys = json.load(open(keys_path))
neutral = np.array(keys["shapes"]["neutral"])
stable = np.array(keys["stable"])
names, blocks = [], []
for region in keys["regions"].values():
    idx = np.array(region["indices"])
    deltas = np.array([np.array(keys["shapes"][k["name"]]) - neutral[idx] for k in region["keys"]])  # region points
    names += [k["name"] for k in region["keys"]]
    blocks.append((idx, deltas.reshape(len(deltas), -1).T))

def umeyama(src, dst):  # dst ≈ s R src + t
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sv, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.ones(3); d[-1] = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    r = u @ np.diag(d) @ vt
    s = (sv * d).sum() / (a ** 2).sum() * len(src)
    return r, mu_d - s * r @ mu_s, s

with open(out_path, "w", newline="") as fh:
    out = csv.writer(fh)
    out.writerow(["frame", "time", *names])
    for f in range(len(points)):
        p = points[f]
        if not np.isfinite(p).all():
            out.writerow([int(frame_index[f]), f"{times[f]:.6f}", *[""] * len(names)])
            continue
        r, t, s = umeyama(neutral[stable], p[stable])
        canonical = (p - t) @ r / s
        row = []
        for idx, A in blocks:
            w, _ = nnls(A, (canonical[idx] - neutral[idx]).ravel())
            row += [f"{v:.6f}" for v in w]
        out.writerow([int(frame_index[f]), f"{times[f]:.6f}", *row])
'''


def prepare(folder: Path, n_frames: int) -> tuple[Path, Path]:
    """The clip's track tiled to ``n_frames`` (with noise) and its key set; beside it
    ``long_seen.npz``, the same with the clip's visibility tiled too (as ``keyshape track``
    writes a real take: the solve then weights each landmark by it)."""
    import numpy as np

    from keyshape.io import load_track
    from keyshape.io.track import write_track_arrays

    clip_track = folder / "clip.npz"
    subprocess.run([sys.executable, "-m", "keyshape", "track", str(CLIP), "-o", str(clip_track), "-q"], check=True)
    keys = folder / "keys.json"
    subprocess.run([sys.executable, "-m", "keyshape", "keys", str(clip_track), "-o", str(keys), "-q"], check=True)
    track = load_track(clip_track)
    reps = -(-n_frames // track.n_frames)
    rng = np.random.default_rng(0)
    points = np.tile(track.points, (reps, 1, 1))[:n_frames]
    points = (points + rng.normal(0.0, 0.3, points.shape)).astype(np.float32)  # as `keyshape track` writes
    write_track_arrays(folder / "long.npz", points=points, fps=track.fps, image_size=track.image_size,
                       frame_index=np.arange(n_frames), time=np.arange(n_frames) / track.fps)
    if track.visibility is not None:
        write_track_arrays(folder / "long_seen.npz", points=points, fps=track.fps, image_size=track.image_size,
                           frame_index=np.arange(n_frames), time=np.arange(n_frames) / track.fps,
                           visibility=np.tile(track.visibility, (reps, 1))[:n_frames])
    return folder / "long.npz", keys


def warm(path: Path) -> None:
    """Read ``path`` through once, so that the command timed next finds it in the page cache: the
    disk's speed is left out (this machine's virtual disk reads a cold 575 MB track in about 30 s,
    and the files the benchmark writes can push its inputs out of the cache between commands)."""
    with open(path, "rb") as fh:
        while fh.read(1 << 24):
            pass


def wall(command: list[str]) -> tuple[float, float]:
    """(wall seconds, CPU seconds: user + system of the process and its children)."""
    for arg in command:
        if arg.endswith(".npz") and Path(arg).exists():
            warm(Path(arg))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return seconds, after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--profile", action="store_true", help="also print a cProfile of `keyshape solve`")
    args = parser.parse_args(argv)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1")}
    os.environ.update(env)
    with open("/proc/loadavg") as fh:
        load = fh.read().split()[:3]
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"load average {' '.join(load)}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        track, keys = prepare(folder, args.frames)
        (folder / "naive.py").write_text(NAIVE)
        commands = {
            "naive script (Umeyama per frame, scipy nnls loop, csv)":
                [sys.executable, str(folder / "naive.py"), str(track), str(keys), str(folder / "naive.csv")],
            "keyshape solve (default: smoothed, bounded)":
                [sys.executable, "-m", "keyshape", "solve", str(track), str(keys), "-o", str(folder / "w.csv"), "-q"],
            "keyshape solve --smooth 0 (per-frame bounded NNLS)":
                [sys.executable, "-m", "keyshape", "solve", str(track), str(keys), "-o", str(folder / "w0.csv"),
                 "-q", "--smooth", "0"],
        }
        if (folder / "long_seen.npz").exists():
            commands["keyshape solve on the same track with its visibility (a real take)"] = \
                [sys.executable, "-m", "keyshape", "solve", str(folder / "long_seen.npz"), str(keys), "-o",
                 str(folder / "ws.csv"), "-q"]
        if shutil.which("taskset"):
            commands["keyshape solve, pinned to one core (taskset -c 0)"] = \
                ["taskset", "-c", "0", *commands["keyshape solve (default: smoothed, bounded)"]]
        best = {name: float("inf") for name in commands}
        cpu = dict(best)
        for _ in range(args.repeats):
            for name, command in commands.items():
                seconds, used = wall(command)
                best[name], cpu[name] = min(best[name], seconds), min(cpu[name], used)
        base, base_cpu = best[next(iter(commands))], cpu[next(iter(commands))]
        print(f"\n{args.frames:,} frames, best of {args.repeats}\n")
        print("| command | seconds | frames/s | speed-up | CPU seconds (user + sys) | CPU speed-up |\n"
              "|---|---|---|---|---|---|")
        for name, seconds in best.items():
            print(f"| {name} | {seconds:.2f} | {args.frames / seconds:,.0f} | {base / seconds:.1f}x | "
                  f"{cpu[name]:.2f} | {base_cpu / cpu[name]:.1f}x |")
        with open("/proc/loadavg") as fh:
            print(f"\nload average at the end: {' '.join(fh.read().split()[:3])}")
        if args.profile:
            subprocess.run([sys.executable, "-m", "cProfile", "-s", "cumtime", "-m", "keyshape", "solve", str(track),
                            str(keys), "-o", str(folder / "w.csv"), "-q"], check=True)


if __name__ == "__main__":
    main()
