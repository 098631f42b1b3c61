"""Wall time of ``keyshape batch`` on 8 takes: local Ray (one worker per core) vs sequential.

The takes are 8 consecutive cuts of the embedded clip (472 frames -> 8 x 59 frames, 640x360),
run with ``--no-preview`` (the other outputs, pictures and report included, are written).
Each mode runs in a fresh Python process, so both pay keyshape's and MediaPipe's import once;
Ray's start-up (``ray.init`` of a private local instance) and shutdown are timed on their own.

    python benchmarks/bench_batch.py [--takes 8] [--workers N]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path


def make_takes(folder: Path, n_takes: int) -> list[Path]:
    import av
    import numpy as np

    from keyshape.capture.video import iter_frames

    clip = Path(str(resources.files("keyshape").joinpath("data/WolfgangLanger_Pexels.mp4")))
    frames = np.stack([rgb for _, rgb in iter_frames(clip)])
    paths = []
    for i, part in enumerate(np.array_split(frames, n_takes)):
        path = folder / f"take{i:02d}.mp4"
        with av.open(str(path), "w") as out:
            stream = out.add_stream("libx264", rate=24)
            stream.width, stream.height, stream.pix_fmt = part.shape[2], part.shape[1], "yuv420p"
            for image in part:
                out.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
            out.mux(stream.encode())
        paths.append(path)
    return paths


def one_mode(mode: str, takes: Path, outdir: Path, workers: int | None) -> dict:
    """Child process: time one batch; returns the timings in seconds."""
    from threadpoolctl import threadpool_limits

    start = time.perf_counter()
    from keyshape.app import RunOptions, SequentialRunner, batch

    timings = {"import": time.perf_counter() - start}
    if mode == "ray":
        from keyshape.app import RayRunner

        t = time.perf_counter()
        runner = RayRunner(workers=workers).__enter__()
        timings["ray_start"] = time.perf_counter() - t
    else:
        runner = SequentialRunner()
    t = time.perf_counter()
    with threadpool_limits(limits=1, user_api="blas"):  # as the command line does
        rows = batch([takes], outdir, RunOptions(preview=False), runner=runner)
    timings["batch"] = time.perf_counter() - t
    t = time.perf_counter()
    runner.__exit__(None, None, None)
    timings["shutdown"] = time.perf_counter() - t
    timings["ok"] = sum(r.status == "ok" for r in rows)
    timings["frames"] = sum(r.frames or 0 for r in rows)
    return timings


def run_child(mode: str, takes: Path, outdir: Path, workers: int | None) -> dict:
    cmd = [sys.executable, __file__, "--child", mode, "--takes-dir", str(takes), "--out", str(outdir)]
    if workers:
        cmd += ["--workers", str(workers)]
    start = time.perf_counter()
    result = subprocess.run(cmd, capture_output=True, text=True, check=True)
    timings = json.loads(result.stdout.strip().splitlines()[-1])
    timings["process"] = time.perf_counter() - start
    return timings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--takes", type=int, default=8)
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--child", choices=("ray", "sequential"))
    parser.add_argument("--takes-dir", type=Path)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(one_mode(args.child, args.takes_dir, args.out, args.workers)))
        return
    with tempfile.TemporaryDirectory(prefix="bench-batch-") as folder:
        tmp = Path(folder)
        (tmp / "takes").mkdir()
        make_takes(tmp / "takes", args.takes)
        results = {mode: run_child(mode, tmp / "takes", tmp / mode, args.workers)
                   for mode in ("sequential", "ray")}
    report(results, args)


def report(results: dict, args) -> None:
    load = os.getloadavg()[0]
    seq, ray = results["sequential"], results["ray"]
    print(f"\n{args.takes} takes, {seq['frames']} frames in all, {os.cpu_count()} cores, "
          f"load average {load:.1f} at the end, --no-preview\n")
    print("| mode | Ray start-up (s) | batch (s) | Ray shutdown (s) | whole process (s) | takes ok |")
    print("|---|---:|---:|---:|---:|---:|")
    for mode, t in results.items():
        print(f"| {mode} | {t.get('ray_start', 0):.1f} | {t['batch']:.1f} | {t['shutdown']:.1f} | "
              f"{t['process']:.1f} | {t['ok']} |")
    print(f"\nbatch speed-up on Ray: {seq['batch'] / ray['batch']:.2f}x; whole process, Ray start-up "
          f"included: {seq['process'] / ray['process']:.2f}x")


if __name__ == "__main__":
    main()
