"""Benchmark the decompose stage.

1. Per-frame NNLS: :func:`keyshape.decompose.solve_nnls` against a Python loop of
   ``scipy.optimize.nnls`` (the reference), K = 8, 16, 24 keys, 100,000 frames. The scipy loop
   runs on a subset (5,000 frames by default) and is extrapolated linearly; the weights of
   that subset are compared.
2. Spacetime solve: :func:`keyshape.decompose.solve_spacetime` at K = 12 (smoothness 1,
   upper bound 1) in frames per second, against Clarabel through qpsolvers on the same
   problem at a smaller T (the whole sequence as one sparse QP), with the objective gap.
3. Peak memory (tracemalloc) against the number of frames, for both solvers.

Run::

    python benchmarks/bench_decompose.py                 # full run, a markdown report
    python benchmarks/bench_decompose.py --json out.json # also write the numbers
    python benchmarks/bench_decompose.py --quick         # smaller sizes, for a smoke test

The region size defaults to m = 171 (57 landmarks × 3D, the lower-face region of the
upper-lower scheme on MediaPipe's 478 points). OpenBLAS runs single-threaded unless
``OPENBLAS_NUM_THREADS`` is set: its threads only slow the small K × K products down on two
cores (the DESIGN notes measure the same for process pools).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads OpenBLAS

import argparse
import json
import platform
import sys
import time
import tracemalloc
import warnings

import numpy as np
import scipy
import scipy.optimize
from scipy.ndimage import gaussian_filter1d

from keyshape.decompose import solve_nnls, solve_spacetime

# --------------------------------------------------------------------------- synthetic data


def region(m: int, n_keys: int, rng, *, correlation: float = 0.5) -> np.ndarray:
    """Key deltas ``A (m, n_keys)``: equicorrelated columns (a shared component, as real
    expressions share), magnitudes spread over 0.5–2."""
    mix = np.linalg.cholesky((1 - correlation) * np.eye(n_keys) + correlation).T
    A = rng.standard_normal((m, n_keys)) @ mix
    return A * rng.uniform(0.5, 2.0, n_keys) / np.sqrt(m)


def performance(A: np.ndarray, n_frames: int, rng, *, smooth: bool, noise: float = 0.05):
    """Frames ``B (n_frames, m)`` from known weights (about half of them zero) plus noise."""
    k = A.shape[1]
    if smooth:
        Z = gaussian_filter1d(rng.standard_normal((n_frames, k)), 6.0, axis=0)
        W = np.clip(Z / Z.std(axis=0) * 0.5, 0.0, 1.0)
    else:
        W = rng.random((n_frames, k)) * (rng.random((n_frames, k)) < 0.5)
    return W, W @ A.T + noise * rng.standard_normal((n_frames, A.shape[0])) * np.abs(A).mean()


def objective(A, B, W, smoothness):
    """``Σ ‖A w_t − b_t‖² + μ Σ ‖Δ² w‖²``, ``μ = smoothness · trace(AᵀA) / K``."""
    valid = np.isfinite(B).all(axis=1)
    r = (W @ A.T - B)[valid]
    d = W[:-2] - 2 * W[1:-1] + W[2:]
    return float(np.sum(r * r) + smoothness * np.trace(A.T @ A) / A.shape[1] * np.sum(d * d))


def best_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


# --------------------------------------------------------------------------- 1. per-frame


def bench_nnls(n_frames: int, subset: int, m: int, keys=(8, 16, 24), repeats: int = 2):
    rows = []
    for k in keys:
        rng = np.random.default_rng(k)
        A = region(m, k, rng)
        _, B = performance(A, n_frames, rng, smooth=False)
        ours = best_time(lambda A=A, B=B: solve_nnls(A, B), repeats)
        start = time.perf_counter()
        ref = np.array([scipy.optimize.nnls(A, b)[0] for b in B[:subset]])
        loop = (time.perf_counter() - start) / subset * n_frames
        agree = float(np.abs(solve_nnls(A, B[:subset]) - ref).max())
        rows.append({"n_keys": k, "n_frames": n_frames, "m": m, "ours_s": ours, "scipy_loop_s": loop,
                         "scipy_subset": subset, "speedup": loop / ours, "max_abs_diff": agree})
    return rows


# --------------------------------------------------------------------------- 2. spacetime


def bench_spacetime(sizes, clarabel_frames: int, m: int, k: int = 12, smoothness: float = 1.0,
                    repeats: int = 2):
    rng = np.random.default_rng(12)
    A = region(m, k, rng)
    rows = []
    for n in sizes:
        _, B = performance(A, n, np.random.default_rng(n), smooth=True)
        t = best_time(lambda B=B: solve_spacetime(A, B, smoothness=smoothness, upper=1.0), repeats)
        rows.append({"solver": "keyshape", "n_frames": n, "n_keys": k, "seconds": t, "frames_per_s": n / t})
    _, B = performance(A, clarabel_frames, np.random.default_rng(1), smooth=True)
    ours_t = best_time(lambda: solve_spacetime(A, B, smoothness=smoothness, upper=1.0), repeats)
    W = solve_spacetime(A, B, smoothness=smoothness, upper=1.0)
    clar_t, R = clarabel(A, B, smoothness)
    rel = (objective(A, B, W, smoothness) - objective(A, B, R, smoothness)) / objective(A, B, R, smoothness)
    rows.append({"solver": "keyshape", "n_frames": clarabel_frames, "n_keys": k, "seconds": ours_t,
                     "frames_per_s": clarabel_frames / ours_t})
    rows.append({"solver": "clarabel (qpsolvers)", "n_frames": clarabel_frames, "n_keys": k, "seconds": clar_t,
                     "frames_per_s": clarabel_frames / clar_t, "objective_rel_diff_ours_minus_clarabel": rel})
    return rows


def clarabel(A, B, smoothness):
    """The whole sequence as one sparse QP, solved by Clarabel; (seconds incl. setup, W)."""
    import qpsolvers
    from scipy import sparse

    start = time.perf_counter()
    n, k = B.shape[0], A.shape[1]
    G = A.T @ A
    L = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n - 2, n))
    P = sparse.kron(sparse.eye(n), G) + smoothness * np.trace(G) / k * sparse.kron(L.T @ L, sparse.eye(k))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        x = qpsolvers.solve_qp(sparse.csc_matrix(2 * P), -2 * (B @ A).ravel(), lb=np.zeros(n * k),
                               ub=np.ones(n * k), solver="clarabel")
    return time.perf_counter() - start, x.reshape(n, k)


# --------------------------------------------------------------------------- 3. memory


def bench_memory(sizes, m: int, k: int = 12):
    rng = np.random.default_rng(3)
    A = region(m, k, rng)
    rows = []
    for n in sizes:
        _, B = performance(A, n, np.random.default_rng(n), smooth=True)
        for name, fn in (("solve_nnls", lambda B=B: solve_nnls(A, B, upper=1.0)),
                         ("solve_spacetime", lambda B=B: solve_spacetime(A, B, smoothness=1.0, upper=1.0))):
            tracemalloc.start()
            fn()
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            rows.append({"solver": name, "n_frames": n, "n_keys": k, "peak_mb": peak / 2**20,
                             "bytes_per_frame": peak / n})
    return rows


# --------------------------------------------------------------------------- report


def machine():
    return {
        "python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
        "cpus": os.cpu_count(), "load_average": os.getloadavg(),
        "openblas_threads": os.environ.get("OPENBLAS_NUM_THREADS", "(default)"),
        "command": " ".join([os.path.basename(sys.executable)] + sys.argv),
    }


def markdown(result) -> str:
    out = ["## decompose benchmark", "", "```", json.dumps(result["machine"]), "```", ""]
    out += ["### Per-frame NNLS: solve_nnls vs a Python loop of scipy.optimize.nnls", "",
            "| K | frames | m | keyshape (s) | frames/s | scipy loop (s, extrapolated) | speedup | max abs diff |",
            "|---|---|---|---|---|---|---|---|"]
    for r in result["nnls"]:
        out.append(f"| {r['n_keys']} | {r['n_frames']:,} | {r['m']} | {r['ours_s']:.3f} | "
                   f"{r['n_frames'] / r['ours_s']:,.0f} | {r['scipy_loop_s']:.1f} (from {r['scipy_subset']:,}) | "
                   f"{r['speedup']:.1f}× | {r['max_abs_diff']:.1e} |")
    out += ["", "### Spacetime solve (K = 12, smoothness 1, upper 1)", "",
            "| solver | frames | seconds | frames/s | objective (ours − Clarabel) / Clarabel |",
            "|---|---|---|---|---|"]
    for r in result["spacetime"]:
        rel = r.get("objective_rel_diff_ours_minus_clarabel")
        out.append(f"| {r['solver']} | {r['n_frames']:,} | {r['seconds']:.3f} | {r['frames_per_s']:,.0f} | "
                   f"{'' if rel is None else f'{rel:+.1e}'} |")
    out += ["", "### Peak memory (tracemalloc) vs frames, K = 12", "",
            "| solver | frames | peak MB | bytes/frame |", "|---|---|---|---|"]
    for r in result["memory"]:
        out.append(f"| {r['solver']} | {r['n_frames']:,} | {r['peak_mb']:.1f} | {r['bytes_per_frame']:,.0f} |")
    return "\n".join(out)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=100_000, help="frames for the per-frame benchmark")
    parser.add_argument("--subset", type=int, default=5_000, help="frames given to the scipy loop")
    parser.add_argument("--m", type=int, default=171, help="rows of A (landmarks × dims of a region)")
    parser.add_argument("--clarabel-frames", type=int, default=2_000, help="T for the Clarabel comparison")
    parser.add_argument("--json", help="also write the results to this JSON file")
    parser.add_argument("--quick", action="store_true", help="small sizes (a smoke test)")
    args = parser.parse_args(argv)
    if args.quick:
        args.frames, args.subset, args.clarabel_frames = 5_000, 500, 300
    spacetime_sizes = [args.frames // 10, args.frames] if not args.quick else [2_000]
    memory_sizes = [args.frames // 8, args.frames // 4, args.frames // 2, args.frames]
    result = {
        "machine": machine(),
        "nnls": bench_nnls(args.frames, args.subset, args.m),
        "spacetime": bench_spacetime(spacetime_sizes, args.clarabel_frames, args.m),
        "memory": bench_memory(memory_sizes, args.m),
    }
    print(markdown(result))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
