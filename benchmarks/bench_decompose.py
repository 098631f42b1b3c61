"""Benchmark the decompose stage.

1. Per-frame NNLS: :func:`keyshape.decompose._solve.solve_nnls` against a Python loop of
   ``scipy.optimize.nnls`` (the reference), K = 8, 16, 24 keys, 100,000 frames. The scipy loop
   runs on a subset (5,000 frames by default) and is extrapolated linearly; the weights of
   that subset are compared.
2. Spacetime solve: :func:`keyshape.decompose._solve.solve_spacetime` at K = 12 (upper bound 1) in
   frames per second: smoothness 1 and the product's default 0.1, with a tracker's gaps
   (5 % dropped frames, a 15-frame gap per 1,000), with a 60-frame gap every 700 frames, with
   ``convex``, and with a hand over the mouth (visibility weights: the weighted solve of
   :mod:`keyshape.decompose._weighted`, exact active-set steps on its banded Hessian); against Clarabel
   through qpsolvers on the same problem at a smaller T (the whole sequence as one sparse
   QP), with the objective gap.
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
from keyshape.decompose._weighted import solve_weighted  # the visibility-weighted solve of a region

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


def best_time(fn, repeats: int) -> tuple[float, float]:
    """Best (wall, CPU) seconds of ``repeats`` runs. CPU time is what this process used; on a
    shared machine it is the steadier of the two."""
    wall, cpu = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w)
        cpu.append(time.process_time() - c)
    return min(wall), min(cpu)


# --------------------------------------------------------------------------- 1. per-frame


def scipy_loop(A, B):
    """The reference: one ``scipy.optimize.nnls`` call per frame."""
    return np.array([scipy.optimize.nnls(A, b)[0] for b in B])


def bench_nnls(n_frames: int, subset: int, m: int, keys=(8, 16, 24), repeats: int = 3):
    rows = []
    for k in keys:
        rng = np.random.default_rng(k)
        A = region(m, k, rng)
        _, B = performance(A, n_frames, rng, smooth=False)
        ours, ours_cpu = best_time(lambda A=A, B=B: solve_nnls(A, B), repeats)
        ref = []
        loop, loop_cpu = best_time(lambda A=A, B=B, ref=ref: ref.append(scipy_loop(A, B[:subset])), repeats)
        scale = n_frames / subset  # the loop is linear in frames: extrapolate
        agree = float(np.abs(solve_nnls(A, B[:subset]) - ref[0]).max())
        rows.append({"n_keys": k, "n_frames": n_frames, "m": m, "ours_s": ours, "ours_cpu_s": ours_cpu,
                     "scipy_loop_s": loop * scale, "scipy_loop_cpu_s": loop_cpu * scale,
                     "scipy_subset": subset, "speedup_wall": loop * scale / ours,
                     "speedup_cpu": loop_cpu / ours_cpu * scale, "max_abs_diff": agree})
    return rows


# --------------------------------------------------------------------------- 2. spacetime


def tracking_gaps(B: np.ndarray, rng) -> np.ndarray:
    """``B`` with what a face tracker loses: 5 % single dropped frames and a 15-frame gap
    (half a second at 30 fps, the longest the pipeline bridges) every 1,000 frames."""
    B = B.copy()
    B[1:-1][rng.random(len(B) - 2) < 0.05] = np.nan
    for start in range(500, len(B) - 20, 1000):
        B[start : start + 15] = np.nan
    return B


def long_gaps(B: np.ndarray, rng=None) -> np.ndarray:
    """``B`` with a 60-frame gap every 700 frames (half a second at 120 fps: still bridged)."""
    B = B.copy()
    for start in range(300, len(B) - 65, 700):
        B[start : start + 60] = np.nan
    return B


def hand_over_mouth(n_frames: int, m: int, rng, *, n_dims: int = 3) -> np.ndarray:
    """Coordinate weights ``(n_frames, m)`` of a hand over the mouth for 170 frames in every 700
    (as on the embedded clip): 60 % of the region's landmarks hidden (visibility 0.05), and all of
    them for the middle 40 frames (the region then has no data term: a gap)."""
    weight = np.ones((n_frames, m // n_dims))
    for start in range(300, n_frames - 175, 700):
        covered = rng.permutation(m // n_dims)[: int(0.6 * (m // n_dims))]
        weight[start : start + 170, covered] = 0.05
        weight[start + 65 : start + 105] = 0.0
    return np.repeat(weight, n_dims, axis=1)


CASES = {  # name: (smoothness, convex, gaps)
    "smoothness 1": (1.0, False, None),
    "smoothness 0.1 (default)": (0.1, False, None),
    "smoothness 0.1, tracking gaps": (0.1, False, tracking_gaps),
    "smoothness 0.1, 60-frame gaps": (0.1, False, long_gaps),
    "smoothness 0.1, convex": (0.1, True, None),
    "smoothness 0.1, hand over the mouth": (0.1, False, "visibility"),
}


def solve_case(A, data, *, smoothness, convex, tol, weight=None):
    """One case as the solve of a region runs it: with a visibility weight, the weighted solve
    (:mod:`keyshape.decompose._weighted`) around the unweighted one, as ``solve_weights`` does."""
    solve = lambda b: solve_spacetime(A, b, smoothness=smoothness, upper=1.0, convex=convex, tol=tol)  # noqa: E731
    if weight is None:
        return solve(data)
    from keyshape.decompose._solve import _mu

    return solve_weighted(A, data, weight, solve, smoothness=smoothness, upper=np.ones(A.shape[1]), convex=convex,
                          mu=_mu(A.T @ A, smoothness))


def bench_spacetime(sizes, clarabel_frames: int, m: int, k: int = 12, repeats: int = 2):
    rng = np.random.default_rng(12)
    A = region(m, k, rng)
    rows = []

    def row(solver, case, n, times, tol=None, **extra):
        wall, cpu = times
        return {"solver": solver, "case": case, "tol": tol, "n_frames": n, "n_keys": k, "seconds": wall,
                "cpu_seconds": cpu, "frames_per_s": n / wall, "frames_per_cpu_s": n / cpu, **extra}

    _, B = performance(A, 500, np.random.default_rng(0), smooth=True)
    solve_spacetime(A, B, smoothness=1.0, upper=1.0)  # warm-up: loads the compiled kernels
    for n in sizes:
        _, B = performance(A, n, np.random.default_rng(n), smooth=True)
        for case, (smoothness, convex, gaps) in CASES.items():
            data, weight = (0.6 * B if convex else B), None
            if gaps == "visibility":  # the tracker's guesses under the hand: wrong data where hidden
                weight = hand_over_mouth(n, m, np.random.default_rng(n + 2))
                data = B + (weight < 1) * np.random.default_rng(n + 3).normal(0.0, 0.5, B.shape) * np.abs(A).mean()
            elif gaps:
                data = gaps(B, np.random.default_rng(n + 1))
            for tol in (1e-7, 1e-4) if case == "smoothness 1" else (1e-7,):
                t = best_time(lambda data=data, tol=tol, s=smoothness, c=convex, w=weight: solve_case(
                    A, data, smoothness=s, convex=c, tol=tol, weight=w), repeats)
                rows.append(row("keyshape", case, n, t, tol))
    smoothness = 1.0
    _, B = performance(A, clarabel_frames, np.random.default_rng(1), smooth=True)
    t = best_time(lambda: solve_spacetime(A, B, smoothness=smoothness, upper=1.0), repeats)
    W = solve_spacetime(A, B, smoothness=smoothness, upper=1.0)
    out = []
    t_clar = best_time(lambda: out.append(clarabel(A, B, smoothness)), 1)
    ref = objective(A, B, out[0], smoothness)
    rows.append(row("keyshape", "smoothness 1", clarabel_frames, t, 1e-7))
    rows.append(row("clarabel (qpsolvers)", "smoothness 1", clarabel_frames, t_clar,
                    objective_rel_diff_ours_minus_clarabel=(objective(A, B, W, smoothness) - ref) / ref))
    return rows


def clarabel(A, B, smoothness):
    """The whole sequence as one sparse QP (built and) solved by Clarabel: ``W (T, K)``."""
    import qpsolvers
    from scipy import sparse

    n, k = B.shape[0], A.shape[1]
    G = A.T @ A
    L = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n - 2, n))
    P = sparse.kron(sparse.eye(n), G) + smoothness * np.trace(G) / k * sparse.kron(L.T @ L, sparse.eye(k))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        x = qpsolvers.solve_qp(sparse.csc_matrix(2 * P), -2 * (B @ A).ravel(), lb=np.zeros(n * k),
                               ub=np.ones(n * k), solver="clarabel")
    return x.reshape(n, k)


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
    out = ["## decompose benchmark", "", "```", json.dumps(result["machine"]), "```", "",
           "Times are the best of 3 runs (2 for the spacetime rows), as wall-clock seconds and as",
           "CPU seconds of this process (steadier on a shared machine); speedups are given for both.", ""]
    out += ["### Per-frame NNLS: solve_nnls vs a Python loop of scipy.optimize.nnls", "",
            ("| K | frames | m | keyshape wall s (CPU s) | frames/s wall | scipy loop wall s (CPU s) "
            "| speedup wall / CPU | max abs diff |"),
            "|---|---|---|---|---|---|---|---|"]
    for r in result["nnls"]:
        out.append(
            f"| {r['n_keys']} | {r['n_frames']:,} | {r['m']} | {r['ours_s']:.3f} ({r['ours_cpu_s']:.3f}) | "
            f"{r['n_frames'] / r['ours_s']:,.0f} | {r['scipy_loop_s']:.1f} ({r['scipy_loop_cpu_s']:.1f}), "
            f"extrapolated from {r['scipy_subset']:,} | {r['speedup_wall']:.1f}× / {r['speedup_cpu']:.1f}× | "
            f"{r['max_abs_diff']:.1e} |")
    out += ["", "### Spacetime solve (K = 12, upper 1)", "",
            ("| solver | case | tol | frames | wall s | CPU s | frames/s wall | frames/s CPU | "
            "objective (ours − Clarabel) / Clarabel |"),
            "|---|---|---|---|---|---|---|---|---|"]
    for r in result["spacetime"]:
        rel = r.get("objective_rel_diff_ours_minus_clarabel")
        tol = "" if r["tol"] is None else f"{r['tol']:.0e}"
        out.append(f"| {r['solver']} | {r['case']} | {tol} | {r['n_frames']:,} | {r['seconds']:.3f} | "
                   f"{r['cpu_seconds']:.3f} | {r['frames_per_s']:,.0f} | {r['frames_per_cpu_s']:,.0f} | "
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
