"""``keyshape report-k``: reconstruction error against the number of key shapes (the paper's comparison).

For K = 1 … ``--max-k`` and every region, the RMS error of rebuilding the take from K key
shapes chosen by spa (ours), spread and hull (the paper's), with PCA's mean + K components
as the unreachable lower bound; in % of the inter-ocular distance. Writes
``error_vs_k.csv`` (region,method,k,error_pct), ``error_vs_k.png`` and ``error_vs_k.json``
(read by ``keyshape report`` when the folder is a ``keyshape run`` folder).
"""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

from ._argtypes import bound, positive, whole

DESCRIPTION = ("Chuang & Bregler's comparison on a take: per region, the RMS reconstruction error "
               "(% of the inter-ocular distance) for K = 1 ... --max-k key shapes chosen by spa "
               "(ours), spread and hull (the paper's), and PCA with K components (mean + K "
               "components, unconstrained: the lower bound no choice of real frames reaches). Frames "
               "are fitted with 0 <= w <= --max, as `keyshape solve` does. Writes DIR/error_vs_k.csv "
               "(region,method,k,error_pct), DIR/error_vs_k.png and DIR/error_vs_k.json.")

SHOWN_KS = (1, 2, 4, 8, 12, 16, 24, 30)


def add_arguments(p) -> None:
    from ..defaults import DEFAULT_REGIONS, DEFAULT_UPPER, MAX_ERROR

    p.add_argument("track", type=Path, help="track file (.npz with points and fps, or a landmark CSV)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="DIR")
    p.add_argument("--regions", default=DEFAULT_REGIONS, metavar="SCHEME",
                   help="upper-lower (default), whole, eyes, or a REGIONS.json")
    p.add_argument("--max-k", type=whole(1, 200), default=30, metavar="K",
                   help="largest number of key shapes per region (default 30)")
    p.add_argument("--neutral", type=whole(0), default=None, metavar="FRAME",
                   help="the neutral frame; default: chosen automatically as in `keyshape keys`")
    p.add_argument("--max", type=bound, default=DEFAULT_UPPER, metavar="U",
                   help=f"upper bound of the weights in the fits (default {DEFAULT_UPPER:g}, as "
                        "`keyshape solve`; 'none' lifts it: the paper's NNLS)")
    p.add_argument("--max-error", type=positive, default=MAX_ERROR, metavar="PCT",
                   help=f"error target whose K (`--count auto`) is marked and printed (default {MAX_ERROR:g} %%)")


def run(args) -> None:
    from ..alignment import align, choose_neutral
    from ..exceptions import InputError
    from ..io.track import load_track
    from ..keyshapes import check_neutral_frame, error_vs_k
    from ..report.plots import error_vs_k as plot_error_vs_k
    from ..schemes import resolve_regions, stable_points

    track = load_track(args.track)
    if track.valid.sum() < 2:
        raise InputError(f"{args.track}: needs at least 2 frames with a face; has {int(track.valid.sum())}")
    regions = resolve_regions(args.regions, track.n_landmarks)
    stable = stable_points(track.n_landmarks)
    if args.neutral is None:
        neutral = choose_neutral(track, stable=stable)
    else:
        neutral = check_neutral_frame(track, args.neutral, name="--neutral")
    aligned, _ = align(track, reference=track.points[neutral], stable=stable)
    ks = range(1, min(args.max_k, int(aligned.valid.sum()) - 1) + 1)
    start = time.perf_counter()
    curve = error_vs_k(aligned, regions=regions, neutral_frame=neutral, ks=ks, upper=args.max)
    seconds = time.perf_counter() - start
    chosen = _auto_k(curve, args.max_error)
    out = args.output
    _write_csv(curve, out / "error_vs_k.csv")
    _write_json(curve, out / "error_vs_k.json")
    plot_error_vs_k(curve.table, out / "error_vs_k.png", unit=curve.unit,
                    chosen={r: k for r, (k, _) in chosen.items()})
    if not args.quiet:
        print(_summary(curve, chosen, args, seconds))


def _auto_k(curve, max_error: float) -> dict[str, tuple[int, float]]:
    """region -> (K, error): spa's smallest K below ``max_error`` (what ``--count auto`` picks)."""
    from ..defaults import MAX_KEYS

    out = {}
    for region, errors in curve.errors["spa"].items():
        reach = [i for i, k in enumerate(curve.ks) if k <= MAX_KEYS]
        below = [i for i in reach if errors[i] < max_error]
        i = below[0] if below else reach[-1]
        out[region] = (int(curve.ks[i]), float(errors[i]))
    return out


def _write_csv(curve, path: Path) -> None:
    from ..io.atomic import atomic_path

    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["region", "method", "k", "error_pct"])
        for region, method, k, error in curve.rows():
            writer.writerow([region, method, k, f"{error:.6g}"])


def _write_json(curve, path: Path) -> None:
    """``{method: {region: {"ks": [...], "errors": [...]}}}``, the form ``keyshape report`` reads."""
    from ..io.atomic import atomic_path

    data = {m: {r: {"ks": curve.ks.tolist(), "errors": [round(float(e), 6) for e in errors]}
                for r, errors in per_region.items()} for m, per_region in curve.errors.items()}
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1) + "\n")


def _summary(curve, chosen, args, seconds: float) -> str:
    shown = [k for k in SHOWN_KS if k in set(curve.ks.tolist())] or curve.ks.tolist()[:8]
    index = {k: i for i, k in enumerate(curve.ks.tolist())}
    bound = "no bound" if curve.upper is None else f"0 <= w <= {curve.upper:g}"
    head = (f"{args.output}/error_vs_k.csv, .png, .json: neutral frame {curve.neutral_frame}, {bound}, "
            f"RMS error in {curve.unit}, {seconds:.1f} s")
    lines = [head,
             f"{'region':<8} {'method':<7} " + " ".join(f"{'K=' + str(k):>6}" for k in shown)]
    for region in next(iter(curve.errors.values())):
        for method, per_region in curve.errors.items():
            values = " ".join(f"{per_region[region][index[k]]:6.3f}" for k in shown)
            lines.append(f"{region:<8} {method:<7} {values}")
    unit = curve.unit.removeprefix("% ")
    auto = ", ".join(f"{r} K={k} ({e:.2f} %)" for r, (k, e) in chosen.items())
    lines.append(f"--count auto (spa, error < {args.max_error:g} % {unit}): {auto}")
    return "\n".join(lines)
