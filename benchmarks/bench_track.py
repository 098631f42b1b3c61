"""Tracking speed and memory: ``keyshape track`` vs a bare PyAV + MediaPipe loop.

    python benchmarks/bench_track.py                 # speed on the demo clip, memory at 1 and 5 min
    python benchmarks/bench_track.py --minutes 1 5 60  # add a one-hour input (about 25 min here)
    python benchmarks/bench_track.py --repeats 0 --minutes --processes 0 2   # whole processes only

Whole processes (``--processes``): the bare loop as a script and ``keyshape track --workers N``
for N = 1, 2, 4, each a fresh interpreter (imports, model start-up and writing included), on the
demo clip and on it looped to each ``--processes`` length in minutes (0 = the clip itself),
alternated, best of ``--process-repeats`` (with the CPU seconds of that run, workers included); the
scaling with the workers is against ``--workers 1``.

Speed: frames/s of the product's tracker (``track_to_file``: decode thread + MediaPipe + the
per-frame bookkeeping + writing the track) and of the obvious baseline (a plain loop of PyAV
decode and ``detect_for_video``, results discarded) on the same clip, alternated, best of N.
Memory: peak resident set size of ``keyshape track`` in a fresh process on the demo clip looped
to the given lengths (packets remuxed, not re-encoded): the RSS of its largest process, and the
PSS of all its processes together (the parallel track's workers included; shared pages counted
once), sampled every 0.2 s.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import subprocess
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path

CLIP = Path(str(resources.files("keyshape").joinpath("data/WolfgangLanger_Pexels.mp4")))


def bare_loop(path: Path) -> int:
    """PyAV decode + MediaPipe detect_for_video, nothing else."""
    import av
    import mediapipe as mp
    from mediapipe.tasks.python import BaseOptions, vision

    from keyshape.capture import default_model_path

    options = vision.FaceLandmarkerOptions(
        base_options=BaseOptions(model_asset_path=str(default_model_path())),
        running_mode=vision.RunningMode.VIDEO, output_face_blendshapes=True,
        output_facial_transformation_matrixes=True)
    n = 0
    with av.open(str(path)) as container, vision.FaceLandmarker.create_from_options(options) as lm:
        for i, frame in enumerate(container.decode(video=0)):
            image = mp.Image(image_format=mp.ImageFormat.SRGB, data=frame.to_ndarray(format="rgb24"))
            lm.detect_for_video(image, int(i * 1000 / 24))
            n += 1
    return n


def ours(path: Path, out: Path) -> int:
    from keyshape.capture import track_to_file

    return track_to_file(path, out, progress=False)["n_frames"]


def speed(repeats: int) -> tuple[float, float]:
    best = {"bare": 0.0, "ours": 0.0}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            for name in ("bare", "ours"):
                start = time.perf_counter()
                n = bare_loop(CLIP) if name == "bare" else ours(CLIP, Path(tmp) / "t.npz")
                best[name] = max(best[name], n / (time.perf_counter() - start))
    return best["bare"], best["ours"]


BARE_SCRIPT = """
import sys
sys.path[:0] = {path!r}
from bench_track import bare_loop
from pathlib import Path
bare_loop(Path(sys.argv[1]))
"""


def whole_processes(video: Path, folder: Path, repeats: int) -> tuple[dict[str, float], dict[str, float]]:
    """Best wall seconds of each command as a fresh process on ``video``, and its CPU seconds
    (user + system, its worker processes included) in that run."""
    import resource

    script = folder / "bare.py"
    script.write_text(BARE_SCRIPT.format(path=[str(Path(__file__).parent)]))
    commands = {"bare loop": [sys.executable, str(script), str(video)]}
    for workers in (1, 2, 4):
        commands[f"keyshape track --workers {workers}"] = [
            sys.executable, "-m", "keyshape", "track", str(video), "-o", str(folder / "w.npz"), "-q",
            "--workers", str(workers)]
    best, cpu = dict.fromkeys(commands, float("inf")), {}
    for _ in range(repeats):
        for name, command in commands.items():
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            start = time.perf_counter()
            subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
            seconds = time.perf_counter() - start
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            if seconds < best[name]:
                best[name] = seconds
                cpu[name] = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    return best, cpu


def load_average() -> str:
    with open("/proc/loadavg") as fh:
        return " ".join(fh.read().split()[:3])


def looped(minutes: float, folder: Path) -> Path:
    """The demo clip repeated to ``minutes`` long, by remuxing its packets."""
    import av

    out_path = folder / f"looped_{minutes:g}min.mp4"
    with av.open(str(CLIP)) as src:
        stream = src.streams.video[0]
        packets = [p for p in src.demux(stream) if p.dts is not None]
        duration = max(p.pts for p in packets) + packets[1].pts - packets[0].pts
        clip_seconds = float(duration * stream.time_base)
        repeats = max(1, round(minutes * 60 / clip_seconds))
        with av.open(str(out_path), "w") as dst:
            out = dst.add_stream_from_template(stream)
            for r in range(repeats):
                for p in packets:
                    p.pts += duration if r else 0
                    p.dts += duration if r else 0
                    p.stream = out
                    dst.mux(p)
    return out_path


def _tree(pid: int) -> list[int]:
    """``pid`` and all its descendants, read from /proc (Linux)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        for task in Path(f"/proc/{p}/task").glob("*/children"):
            with contextlib.suppress(OSError):
                todo.extend(int(c) for c in task.read_text().split())
    return out


def _pss_kib(pid: int) -> int:
    """Proportional set size of ``pid`` (kiB): its resident pages, each shared page divided among
    the processes sharing it, so the sum over processes is what they hold together."""
    with contextlib.suppress(OSError):
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1])
    return 0


def peak_rss_mib(video: Path, folder: Path) -> tuple[float, float, float, int]:
    """(peak RSS MiB of the largest process, peak summed PSS MiB of the whole process tree sampled
    every 0.2 s, seconds, frames) of `keyshape track` in a fresh process. The workers of a parallel
    track are processes of their own: the largest one alone is not what the machine holds."""
    import threading

    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "keyshape", "track", str(video), "-o",
                             str(folder / "t.npz"), "-q"])
    total = [0]
    done = threading.Event()

    def sample():
        while not done.is_set():
            total[0] = max(total[0], sum(_pss_kib(p) for p in _tree(proc.pid)))
            done.wait(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    _, status, usage = os.wait4(proc.pid, 0)
    done.set()
    sampler.join()
    if status != 0:
        raise SystemExit(f"keyshape track failed on {video}")
    import numpy as np

    with np.load(folder / "t.npz") as data:
        frames = data["points"].shape[0]
    return usage.ru_maxrss / 1024, total[0] / 1024, time.perf_counter() - start, frames


def probe_frames(video: Path) -> int:
    from keyshape.capture import probe

    return probe(video).n_frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--minutes", type=float, nargs="*", default=[1, 5])
    parser.add_argument("--processes", type=float, nargs="*", default=[0, 2],
                        help="lengths (minutes, 0 = the clip) for the whole-process comparison")
    parser.add_argument("--process-repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"load average {load_average()}")
    with tempfile.TemporaryDirectory() as tmp:
        for minutes in args.processes:
            video = looped(minutes, Path(tmp)) if minutes else CLIP
            best, cpu = whole_processes(video, Path(tmp), args.process_repeats)
            frames = probe_frames(video)
            bare = best["bare loop"]
            print(f"\nwhole processes on {video.name} ({frames} frames), best of {args.process_repeats}, "
                  f"load average after: {load_average()}\n")
            one = best["keyshape track --workers 1"]
            print("| command | seconds | CPU seconds | frames/s | vs bare loop | vs --workers 1 |\n"
                  "|---|---|---|---|---|---|")
            for name, seconds in best.items():
                scaling = f"{one / seconds:.2f}x" if name.startswith("keyshape") else ""
                print(f"| {name} | {seconds:.2f} | {cpu[name]:.1f} | {frames / seconds:.1f} | {bare / seconds:.2f}x "
                      f"| {scaling} |", flush=True)
    if args.repeats > 0:
        bare, fast = speed(args.repeats)
        print("\n| tracker | frames/s | ratio |\n|---|---|---|")
        print(f"| bare PyAV decode + detect_for_video loop | {bare:.1f} | 1.00 |")
        print(f"| keyshape track_to_file | {fast:.1f} | {fast / bare:.2f} |")
    print("\n| input length | frames | peak RSS, largest process (MiB) | peak PSS, all processes (MiB) "
          "| wall time (s) |"
          "\n|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for minutes in args.minutes:
            video = looped(minutes, Path(tmp))
            rss, tree, seconds, frames = peak_rss_mib(video, Path(tmp))
            print(f"| {minutes:g} min | {frames} | {rss:.0f} | {tree:.0f} | {seconds:.0f} |", flush=True)
            video.unlink()


if __name__ == "__main__":
    main()
