"""keyshape live: the causal smoother against the offline zero-lag solve, and the live latency.

1. **Smoothing** (choosing ``DEFAULT_SMOOTHING``). The demo clip (472 frames, 640×360, 23.976 fps)
   is tracked once; its key shapes are discovered as ``keyshape run`` does. The per-frame bounded
   NNLS of every frame is exactly what the live solver computes before its filter (same
   landmarks: MediaPipe's VIDEO mode on the same frames), so each One Euro setting is applied
   to it causally, frame by frame, and compared with the offline zero-lag smoothed solve
   (``solve_take``'s default) over the keys that move (std ≥ 0.02 there):

   * **error**: RMS difference from the zero-lag weights;
   * **jitter**: RMS second difference of the weights per frame (the zero-lag solve's own is
     given beside it);
   * **lag**: the shift (frames, sub-frame by a parabola through the peak) that best lines the
     weights up with the zero-lag ones, averaged over those keys.

2. **Latency**: ``run_live`` on the clip played as a camera (real time), with VMC and Live Link
   outputs sending to UDP ports on 127.0.0.1: frame arrival -> the last packet sent, p50 and p99,
   and MediaPipe's own detect time beside it; frames dropped.

    python benchmarks/bench_live.py                 # both parts
    python benchmarks/bench_live.py --skip-latency
"""

from __future__ import annotations

import argparse
import os
import socket
import time
from importlib import resources
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from keyshape.app import discover_keys, solve_take
from keyshape.capture import OneEuro, track_video

CLIP = Path(str(resources.files("keyshape").joinpath("data/WolfgangLanger_Pexels.mp4")))
CUTOFFS = (0.5, 1.0, 2.0, 3.0, 5.0, 8.0)
BETAS = (0.0, 0.3, 1.0, 3.0)


def causal(raw: np.ndarray, fps: float, min_cutoff: float, beta: float, upper: float = 1.0) -> np.ndarray:
    """The live solver's filter over a take, frame by frame (NaN frames restart it)."""
    step = OneEuro(fps, min_cutoff=min_cutoff, beta=beta)
    return np.stack([np.clip(step(w), 0.0, upper) if np.isfinite(w).all() else step(w) for w in raw])


def lag_frames(live: np.ndarray, reference: np.ndarray, max_lag: int = 10) -> float:
    """Shift (frames) of ``live`` behind ``reference`` at the peak of their cross-correlation."""
    a, b = live - live.mean(), reference - reference.mean()
    n = len(a)
    shifts = np.arange(-max_lag, max_lag + 1)
    corr = np.array([np.dot(a[s:], b[: n - s]) if s >= 0 else np.dot(a[: n + s], b[-s:]) for s in shifts])
    k = int(np.argmax(corr))
    if 0 < k < len(corr) - 1:  # parabola through the peak
        y0, y1, y2 = corr[k - 1 : k + 2]
        return float(shifts[k] + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2))
    return float(shifts[k])


def correlation(live: np.ndarray, per_frame: np.ndarray, moving: np.ndarray) -> float:
    """Mean Pearson correlation over the keys that move (as tests/test_live.py measures it)."""
    ok = np.isfinite(live).all(axis=1) & np.isfinite(per_frame).all(axis=1)
    return float(np.mean([np.corrcoef(live[ok, k], per_frame[ok, k])[0, 1] for k in np.flatnonzero(moving)]))


def measures(live: np.ndarray, reference: np.ndarray, moving: np.ndarray, raw: np.ndarray) -> dict[str, float]:
    corr = correlation(live, raw, moving)
    ok = np.isfinite(live).all(axis=1) & np.isfinite(reference).all(axis=1)
    live, reference = live[ok][:, moving], reference[ok][:, moving]
    return {"corr": corr, "error": float(np.sqrt(np.mean((live - reference) ** 2))),
            "jitter": float(np.sqrt(np.mean(np.diff(live, 2, axis=0) ** 2))),
            "lag": float(np.mean([lag_frames(live[:, k], reference[:, k]) for k in range(live.shape[1])]))}


def smoothing_table(track, keys) -> list[dict]:
    raw = solve_take(track, keys, smoothness=0.0).weights.values
    reference = solve_take(track, keys).weights.values
    moving = np.nanstd(reference, axis=0) >= 0.02
    rows = [{"setting": "zero-lag offline (reference)", **measures(reference, reference, moving, raw)},
            {"setting": "none (raw per-frame)", **measures(raw, reference, moving, raw)}]
    for cutoff in CUTOFFS:
        for beta in BETAS:
            rows.append({"setting": f"{cutoff:g},{beta:g}", "bound_ms": 1000 / (2 * np.pi * cutoff),
                         **measures(causal(raw, track.fps, cutoff, beta), reference, moving, raw)})
    print(f"{int(moving.sum())} of {keys.n_keys} keys move (std >= 0.02 in the zero-lag solve)")
    return rows


def choose(rows: list[dict]) -> str:
    """The rule behind ``DEFAULT_SMOOTHING``: the least lag among the settings whose jitter is at most
    10 % above the zero-lag solve's own."""
    allowed = 1.1 * rows[0]["jitter"]
    return min((r for r in rows[2:] if r["jitter"] <= allowed), key=lambda r: r["lag"])["setting"]


def _udp_sink() -> tuple[socket.socket, int]:
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    sink.setblocking(False)
    return sink, sink.getsockname()[1]


def latency(keys, *, smoothing=None, rate: float | None = None, cores=None) -> dict[str, float]:
    from keyshape.live import DEFAULT_SMOOTHING, LiveLinkSender, Session, VmcSender, open_source, run_live
    from keyshape.targets import Mapping

    arkit = {name: {"jawOpen": 1.0} for name in keys.names[:1]}  # one ARKit target for Live Link
    mapping = Mapping.from_dict({**arkit, **{n: {n: 1.0} for n in keys.names[1:]}})
    (vmc_sink, vmc_port), (ll_sink, ll_port) = _udp_sink(), _udp_sink()

    def setup(k):
        return Session([VmcSender("127.0.0.1", vmc_port, names=mapping.targets),
                        LiveLinkSender("127.0.0.1", ll_port, names=mapping.targets, fps=24)], mapping)

    source = open_source(str(CLIP), fps=rate)
    began = time.perf_counter()
    summary = run_live(source, setup, keys=keys, smoothing=smoothing or DEFAULT_SMOOTHING, cores=cores,
                       say=lambda _: None)
    wall = time.perf_counter() - began
    vmc_sink.close(), ll_sink.close()
    ms, detect = 1000 * summary.latency, 1000 * summary.detect
    rest = ms - detect
    return {"frames": summary.delivered, "processed": summary.processed, "dropped": summary.dropped,
            "p50": np.percentile(ms, 50), "p99": np.percentile(ms, 99), "max": ms.max(),
            "detect_p50": np.percentile(detect, 50), "detect_p99": np.percentile(detect, 99),
            "rest_p50": np.percentile(rest, 50), "rest_p99": np.percentile(rest, 99),
            "live_s": summary.seconds, "wall_s": wall, "load": os.getloadavg()[0]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--skip-latency", action="store_true")
    parser.add_argument("--repeats", type=int, default=2, help="latency runs (default 2)")
    args = parser.parse_args()
    track = track_video(CLIP, progress=False)
    keys = discover_keys(track, take=CLIP.name)
    print(f"{CLIP.name}: {track.n_frames} frames at {track.fps:.3f} fps, {keys.n_keys} keys")
    rows = smoothing_table(track, keys)
    print("| One Euro MINCUT,BETA | lag bound (ms) | error vs zero-lag | jitter | lag (frames) | corr. per-frame |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        bound = f"{row['bound_ms']:.0f}" if "bound_ms" in row else "-"
        print(f"| {row['setting']} | {bound} | {row['error']:.4f} | {row['jitter']:.4f} | {row['lag']:.2f} | "
              f"{row['corr']:.3f} |")
    print(f"chosen (least lag with jitter <= 1.1 x the zero-lag solve's): {choose(rows)}")
    if args.skip_latency:
        return
    print("| run | fps | cores | frames | processed | dropped | latency p50 / p99 / max (ms) | MediaPipe p50 / p99 | "
          "the rest p50 / p99 | live s | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for run in range(args.repeats):
        for rate in (None, 30.0):
            for cores in (None, (0, 1)):
                r = latency(keys, rate=rate, cores=cores)
                print(f"| {run + 1} | {rate or 23.976:g} | {'pinned 0 / 1' if cores else 'free'} | {r['frames']} | "
                      f"{r['processed']} | {r['dropped']} | {r['p50']:.1f} / {r['p99']:.1f} / {r['max']:.1f} | "
                      f"{r['detect_p50']:.1f} / {r['detect_p99']:.1f} | {r['rest_p50']:.2f} / {r['rest_p99']:.2f} | "
                      f"{r['live_s']:.1f} | {r['load']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
