"""What a take found and how well it fits: numbers, pictures, preview, in one ``report.html``.

:func:`write_take_extras` turns an output folder of ``keyshape run`` (``take.json``,
``track.npz``, ``keys.json``, ``weights.csv``, ``animation.glb``) into ``preview.mp4``,
``keyshapes.png``, ``weights.png`` (and ``error_vs_k.png`` when a table is given) and a
self-contained ``report.html``: pictures embedded as data URIs, no network needed.

Fit quality (:func:`fit_quality`) is measured per frame and region on the aligned
landmarks ``x`` against the blend the weights reach, ``x̂ = neutral + Σ_k w_k δ_k``
(Chuang & Bregler 2002, Eq. 1):

* **error** — RMS over the region's landmarks of ``|x − x̂|``, in % of the inter-ocular
  distance (outer eye corners of the neutral shape, :func:`keyshape.schemes.eye_corners`).
* **cost of w ≥ 0** — ``sqrt(error² − error_ls²)`` where ``error_ls`` is the residual of the
  best *unconstrained* blend of the same keys. Both fits lie in the span of the key deltas,
  so by Pythagoras this is the distance from the reached blend to the best linear one: the
  part of the error due to the non-negativity (and any bounds or smoothing) of the weights.
* **outside the hull** — a frame whose cost of w ≥ 0 exceeds ``tolerance`` (default 1.5 %
  of the inter-ocular distance, about the tracker's jitter): the key shapes could only
  reach it with negative weights, so it lies outside the cone the key shapes span from the
  neutral. Such frames are the ones an extra key shape would fix.
"""

from __future__ import annotations

import base64
import html
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .containers import KeyShapes, Track, Weights
from .exceptions import InputError
from .filters import find_gaps
from .io.atomic import atomic_path
from .metrics import face_scale as metrics_face_scale
from .schemes import stable_points

__all__ = ["FitQuality", "fit_quality", "face_scale", "gap_runs", "take_numbers", "write_report",
           "write_take_extras", "write_take_preview", "TakeExtras", "HULL_TOLERANCE"]

HULL_TOLERANCE = 1.5  # % of the inter-ocular distance


@dataclass(frozen=True, eq=False)
class FitQuality:
    """Per-frame fit quality of each region.

    Attributes
    ----------
    error : dict str -> (n_frames,) float
        RMS landmark residual, in ``unit``; NaN where the frame has no face or no weights.
    excess : dict str -> (n_frames,) float
        The part of ``error`` due to the constraints on the weights (cost of w ≥ 0), in ``unit``.
    outside : dict str -> (n_frames,) bool
        ``excess > tolerance``: the frame lies outside the key-shape hull of the region.
    scale : float
        The length that is 100 ``unit`` (inter-ocular distance), in aligned coordinates.
    unit : str
    tolerance : float
    """

    error: dict[str, np.ndarray]
    excess: dict[str, np.ndarray]
    outside: dict[str, np.ndarray]
    scale: float
    unit: str = "% inter-ocular"
    tolerance: float = HULL_TOLERANCE
    regions: tuple[str, ...] = field(default=())


def face_scale(keys: KeyShapes) -> tuple[float, str]:
    """(length, unit) errors are measured against: :func:`keyshape.metrics.face_scale` of the neutral."""
    return metrics_face_scale(keys.neutral)


def fit_quality(aligned: Track, keys: KeyShapes, weights: Weights, *,
                tolerance: float = HULL_TOLERANCE) -> FitQuality:
    """Per-frame reconstruction error, cost of the non-negativity, and frames outside the hull.

    Parameters
    ----------
    aligned : Track
        ``points (n_frames, n_landmarks, d)`` in the key shapes' canonical coordinates.
    keys : KeyShapes
    weights : Weights
        ``values (n_frames, n_keys)`` with a column for every key name (any order).
    tolerance : float, keyword-only
        Cost of w ≥ 0 above which a frame counts as outside the hull, in % of the inter-ocular distance.

    Returns
    -------
    FitQuality

    Examples
    --------
    >>> from keyshape.datasets import make_performance
    >>> from keyshape.align import align
    >>> from keyshape.keyshapes import find_keyshapes
    >>> perf = make_performance(noise=0.0)
    >>> aligned, _ = align(perf.track, reference=perf.neutral, stable=perf.stable)
    >>> keys = find_keyshapes(aligned, regions=perf.regions, n_keys=2, neutral_frame=perf.neutral_frame)
    >>> w = Weights(np.zeros((aligned.n_frames, keys.n_keys)), keys.names, 30.0)
    >>> fit = fit_quality(aligned, keys, w)
    >>> sorted(fit.error), fit.error["upper"].shape
    (['lower', 'upper'], (200,))
    """
    if aligned.points.shape[1:] != keys.neutral.shape:
        raise InputError(f"aligned points {aligned.points.shape[1:]} do not match the key shapes "
                         f"{keys.neutral.shape}")
    values = _key_columns(weights, keys, aligned.n_frames)
    scale, unit = face_scale(keys)
    error, excess = {}, {}
    for region in keys.regions:
        error[region], excess[region] = _region_fit(aligned.points, keys, region, values, 100 / scale)
    outside = {r: np.nan_to_num(excess[r]) > tolerance for r in keys.regions}
    return FitQuality(error, excess, outside, scale, unit, float(tolerance), tuple(keys.regions))


def _key_columns(weights: Weights, keys: KeyShapes, n_frames: int) -> np.ndarray:
    """(n_frames, n_keys) weights in key order."""
    missing = [n for n in keys.names if n not in weights.names]
    if missing or weights.n_frames != n_frames:
        raise InputError(f"weights must have {n_frames} frames and a column per key; got "
                         f"{weights.n_frames} frames, missing {missing}")
    return weights.values[:, [weights.names.index(n) for n in keys.names]]


def _region_fit(points, keys: KeyShapes, region: str, values, to_unit: float):
    """(error, excess) ``(n_frames,)`` of one region, in the report's unit."""
    lm, k = keys.regions[region], keys.keys_of(region)
    targets = points[:, lm] - keys.neutral[lm]  # (n_frames, n_region_landmarks, d)
    bases = keys.deltas[k][:, lm]  # (n_region_keys, n_region_landmarks, d)
    # f: frame, k: key, p: landmark, d: dimension
    reached = np.einsum("fk,kpd->fpd", values[:, k], bases)
    error = np.sqrt(((targets - reached) ** 2).sum(axis=2).mean(axis=1))
    flat_t, flat_b = targets.reshape(len(targets), -1), bases.reshape(len(k), -1)
    ok = np.isfinite(flat_t).all(axis=1)
    best = np.full(len(targets), np.nan)
    if ok.any() and len(k):
        w_ls = np.linalg.lstsq(flat_b.T, flat_t[ok].T, rcond=None)[0].T  # min |t − wᵀB|, no constraints
        best[ok] = np.sqrt(((flat_t[ok] - w_ls @ flat_b) ** 2).sum(axis=1) / len(lm))
    elif ok.any():
        best[ok] = error[ok]
    excess = np.sqrt(np.maximum(error**2 - best**2, 0.0))
    return error * to_unit, excess * to_unit


def gap_runs(valid: np.ndarray) -> tuple[int, int]:
    """(number of runs of frames without a face, length of the longest run).

    Examples
    --------
    >>> gap_runs(np.array([True, False, False, True, False]))
    (2, 2)
    """
    gaps = find_gaps(valid)
    return len(gaps), max((n for _, n in gaps), default=0)


def take_numbers(track: Track, keys: KeyShapes, fit: FitQuality) -> dict:
    """The report's numbers as a JSON-ready dict: frames, detection, gaps, K, errors per region."""
    n_gaps, longest = gap_runs(track.valid)
    regions = {}
    for region in keys.regions:
        err = fit.error[region][np.isfinite(fit.error[region])]
        regions[region] = {
            "keys": int(len(keys.keys_of(region))),
            "landmarks": int(len(keys.regions[region])),
            "rms_error": _round(np.sqrt(np.mean(err**2))) if err.size else None,
            "p95_error": _round(np.percentile(err, 95)) if err.size else None,
            "max_error": _round(err.max()) if err.size else None,
            "frames_outside_hull": int(fit.outside[region].sum()),
        }
    return {
        "frames": track.n_frames, "fps": _round(track.fps, 3), "duration_s": _round(track.n_frames / track.fps, 2),
        "frames_with_face": int(track.valid.sum()),
        "detection_rate": _round(track.valid.mean() * 100 if track.n_frames else 0.0, 2),
        "gaps": n_gaps, "longest_gap_frames": longest, "longest_gap_s": _round(longest / track.fps, 2),
        "neutral_frame": int(keys.neutral_frame), "method": keys.method, "n_keys": keys.n_keys,
        "error_unit": fit.unit, "hull_tolerance": fit.tolerance, "regions": regions,
    }


def _round(value, digits: int = 3):
    return None if value is None or not np.isfinite(value) else round(float(value), digits)


# --------------------------------------------------------------------------- HTML


def _data_uri(path: Path, mime: str) -> str:
    return f"data:{mime};base64," + base64.b64encode(Path(path).read_bytes()).decode("ascii")


_CSS = """
body{font:15px/1.45 system-ui,sans-serif;margin:0 auto;max-width:1180px;padding:18px 24px;color:#1d1f23}
h1{font-size:22px;margin:6px 0 2px} h2{font-size:17px;margin:26px 0 8px;border-bottom:1px solid #ddd}
.sub{color:#666;margin:0 0 12px} table{border-collapse:collapse;margin:6px 0}
td,th{padding:3px 10px;border-bottom:1px solid #eee;text-align:left} th{background:#f5f5f7}
td.n{text-align:right;font-variant-numeric:tabular-nums} img,video{max-width:100%;border:1px solid #ddd}
.note{color:#555;font-size:13px} code{background:#f3f3f5;padding:0 3px}
"""


def write_report(path, numbers: dict, keys: KeyShapes, *, title: str, images: dict[str, Path],
                 video: str | None = None, notes: list[str] | None = None) -> Path:
    """Write a self-contained HTML report, atomically.

    Parameters
    ----------
    path : str or Path
        Output ``report.html``.
    numbers : dict
        From :func:`take_numbers`.
    keys : KeyShapes
    title : str, keyword-only
    images : dict caption -> Path, keyword-only
        PNGs to embed (as base64 data URIs), in order.
    video : str, optional, keyword-only
        The preview video as a path relative to the report, or a ``data:`` URI.
    notes : list of str, optional, keyword-only
        Extra remarks (e.g. a missing source video), shown under the title.

    Returns
    -------
    Path
    """
    parts = [f"<h1>{html.escape(title)}</h1>", _subtitle(numbers)]
    parts += [f'<p class="note">{html.escape(n)}</p>' for n in notes or []]
    parts += ["<h2>Numbers</h2>", _numbers_table(numbers), _regions_table(numbers)]
    if video:
        parts += ["<h2>Preview</h2>", f'<video controls loop muted preload="metadata" src="{html.escape(video)}">'
                  "</video>", '<p class="note">Left: the source video with the tracked landmarks (one colour '
                  "per region). Right: the character driven by the same weights and head rotation. "
                  "Bottom: the current key-shape weights.</p>"]
    for caption_text, png in images.items():
        parts += [f"<h2>{html.escape(caption_text)}</h2>",
                  f'<img alt="{html.escape(caption_text)}" src="{_data_uri(png, "image/png")}">']
    parts += ["<h2>Key shapes</h2>", _keys_table(keys, numbers["fps"]), _definitions(numbers)]
    data = json.dumps(numbers).replace("</", "<\\/")
    document = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
                f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>\n"
                + "\n".join(parts)
                + f'\n<script type="application/json" id="numbers">{data}</script>\n</body></html>\n')
    with atomic_path(path) as tmp:
        tmp.write_text(document, encoding="utf-8")
    return Path(path)


def _subtitle(n: dict) -> str:
    return (f'<p class="sub">{n["frames"]} frames at {n["fps"]:g} fps ({n["duration_s"]:g} s) · '
            f'{n["n_keys"]} key shapes ({html.escape(str(n["method"]))}) · neutral frame {n["neutral_frame"]}</p>')


def _numbers_table(n: dict) -> str:
    rows = [("frames", n["frames"]), ("frames with a face", n["frames_with_face"]),
            ("detection rate", f'{n["detection_rate"]:.2f} %'), ("gaps (runs of frames without a face)", n["gaps"]),
            ("longest gap", f'{n["longest_gap_frames"]} frames ({n["longest_gap_s"]:g} s)'),
            ("neutral frame", n["neutral_frame"]), ("key shapes in all", n["n_keys"])]
    body = "".join(f'<tr><th>{html.escape(k)}</th><td class="n" data-key="{html.escape(k)}">{v}</td></tr>'
                   for k, v in rows)
    return f'<table id="take">{body}</table>'


def _regions_table(n: dict) -> str:
    unit = html.escape(n["error_unit"])
    head = (f"<tr><th>region</th><th>K</th><th>landmarks</th><th>RMS error ({unit})</th>"
            f"<th>95th percentile</th><th>max</th><th>frames outside the hull</th></tr>")
    rows = "".join(
        f'<tr data-region="{html.escape(r)}"><th>{html.escape(r)}</th><td class="n">{v["keys"]}</td>'
        f'<td class="n">{v["landmarks"]}</td><td class="n">{_fmt(v["rms_error"])}</td>'
        f'<td class="n">{_fmt(v["p95_error"])}</td><td class="n">{_fmt(v["max_error"])}</td>'
        f'<td class="n">{v["frames_outside_hull"]}</td></tr>' for r, v in n["regions"].items())
    return f'<table id="regions">{head}{rows}</table>'


def _fmt(value) -> str:
    return "–" if value is None else f"{value:.2f}"


def _keys_table(keys: KeyShapes, fps: float) -> str:
    rows = "".join(f"<tr><td>{html.escape(keys.names[k])}</td><td>{html.escape(keys.key_regions[k])}</td>"
                   f'<td class="n">{int(keys.frames[k])}</td><td class="n">{keys.frames[k] / fps:.2f} s</td>'
                   f"<td>{html.escape(keys.takes[k])}</td></tr>" for k in range(keys.n_keys))
    return ('<table id="keys"><tr><th>name</th><th>region</th><th>frame</th><th>time</th><th>take</th></tr>'
            f"{rows}</table>")


def _definitions(n: dict) -> str:
    unit = html.escape(n["error_unit"])
    return (
        "<h2>How the numbers are defined</h2><ul class=\"note\">"
        f"<li><b>Error</b>: per frame and region, the RMS over the region's landmarks of the distance between "
        f"the aligned landmarks and the blend the weights reach (neutral + Σ w·δ), in {unit} (the neutral "
        "face's outer eye corners). The table gives the RMS over all frames with a face.</li>"
        "<li><b>Cost of w ≥ 0</b> (dotted): √(error² − error<sub>ls</sub>²), where error<sub>ls</sub> is the "
        "residual of the best blend of the same key shapes with unconstrained weights — the part of the "
        "error due to the weights being non-negative (and bounded or smoothed).</li>"
        f"<li><b>Outside the hull</b>: frames whose cost of w ≥ 0 exceeds {n['hull_tolerance']:g} {unit}; "
        "the key shapes reach them only with negative weights. They are shaded in the weight curves; "
        "another key shape from among them would reduce the error.</li>"
        "<li><b>Gaps</b>: maximal runs of consecutive frames in which no face was found.</li></ul>")


# --------------------------------------------------------------------------- the take folder


@dataclass(frozen=True)
class TakeExtras:
    """What :func:`write_take_extras` wrote (None for what it could not make)."""

    report: Path
    preview: Path | None
    pictures: dict[str, Path]
    numbers: dict


def write_take_extras(outdir, *, progress: bool = True, preview: bool = True, backend: str = "auto",
                      k_table: dict | None = None, tolerance: float = HULL_TOLERANCE,
                      embed_video: bool = False) -> TakeExtras:
    """Write ``preview.mp4``, the PNGs and ``report.html`` into an output folder of ``keyshape run``.

    Parameters
    ----------
    outdir : str or Path
        Holds ``take.json`` and the files it names (track, keys, weights, animation).
    progress : bool, keyword-only
        Show a progress bar while rendering the preview.
    preview : bool, keyword-only
        Render ``preview.mp4`` (the slow part).
    backend : "auto", "gl" or "numpy", keyword-only
        Renderer for the preview (see :func:`keyshape.render.make_renderer`).
    k_table : dict, optional, keyword-only
        Error against K, ``{method: {region: (ks, errors)}}`` (see :func:`keyshape.plots.error_vs_k`),
        errors in % of the inter-ocular distance; default: ``error_vs_k.json`` in ``outdir`` if present.
    tolerance : float, keyword-only
        See :func:`fit_quality`.
    embed_video : bool, keyword-only
        Embed the preview in ``report.html`` (base64) instead of linking ``preview.mp4`` beside it.

    Returns
    -------
    TakeExtras
    """
    outdir = Path(outdir)
    take = _load_take(outdir)
    fit = fit_quality(take.aligned, take.keys, take.weights, tolerance=tolerance)
    numbers = take_numbers(take.track, take.keys, fit)
    pictures = _pictures(outdir, take, fit, k_table)
    notes = [] if take.video is not None else [f"The source video {take.info.get('video')!r} was not found: "
                                               "landmarks are drawn on a blank background."]
    movie = _preview(outdir, take, progress=progress, backend=backend) if preview else None
    if not preview and (outdir / "preview.mp4").is_file():
        movie = outdir / "preview.mp4"  # from an earlier run
    if preview and movie is None:
        notes.append(f"No preview: {take.info['files'].get('animation', 'animation.glb')} is missing.")
    report = write_report(outdir / "report.html", numbers, take.keys, title=f"keyshape · {take.name}",
                          images={_CAPTIONS[k]: p for k, p in pictures.items()},
                          video=_video_source(movie, embed_video), notes=notes)
    return TakeExtras(report, movie, pictures, numbers)


def _video_source(movie: Path | None, embed: bool) -> str | None:
    if movie is None:
        return None
    return _data_uri(movie, "video/mp4") if embed else movie.name


_CAPTIONS = {"keyshapes": "Key shapes: the sculpt list", "weights": "Weights over time and fit error",
             "error_vs_k": "Error against the number of key shapes"}


@dataclass(frozen=True)
class _Take:
    info: dict
    name: str
    video: Path | None
    track: Track
    keys: KeyShapes
    weights: Weights
    aligned: Track


def _load_take(outdir: Path) -> _Take:
    from .align import align
    from .io.keys_json import load_keys
    from .io.take import load_take_info
    from .io.track import load_track
    from .io.weights_csv import load_weights_csv

    info = load_take_info(outdir)
    files = info.get("files") or {}
    track = load_track(outdir / files.get("track", "track.npz"))
    keys = load_keys(outdir / files.get("keys", "keys.json"))
    weights = load_weights_csv(outdir / files.get("weights", "weights.csv"))
    if weights.n_frames != track.n_frames:
        raise InputError(f"{outdir}: the weights have {weights.n_frames} frames but the track has {track.n_frames}")
    aligned, _ = align(track, reference=keys.neutral, stable=_stable(keys))
    video = Path(info["video"]) if info.get("video") and Path(info["video"]).is_file() else None
    name = Path(info["video"]).name if info.get("video") else outdir.name
    return _Take(info, name, video, track, keys, weights, aligned)


def _pictures(outdir: Path, take: _Take, fit: FitQuality, k_table) -> dict[str, Path]:
    from . import plots

    frames = [int(take.keys.neutral_frame), *take.keys.frames.tolist()]
    images = _read_frames(take.video, frames)
    names = (take.name, take.info.get("files", {}).get("track", "track.npz"))
    out = {"keyshapes": plots.contact_sheet(take.keys, take.track, images, outdir / "keyshapes.png",
                                            take=names),
           "weights": plots.weight_curves(take.weights, take.keys, fit, outdir / "weights.png")}
    k_table = k_table if k_table is not None else _read_k_table(outdir / "error_vs_k.json")
    if k_table:
        chosen = {r: len(take.keys.keys_of(r)) for r in take.keys.regions}
        out["error_vs_k"] = plots.error_vs_k(k_table, outdir / "error_vs_k.png", unit=fit.unit, chosen=chosen)
    return out


def _read_frames(video: Path | None, frames: list[int]) -> dict[int, np.ndarray]:
    """The video frames with the given indices (none without a video)."""
    if video is None or not frames:
        return {}
    from .capture.video import iter_frames

    wanted, found = set(frames), {}
    source = iter_frames(video)
    try:
        for index, (_, rgb) in enumerate(source):
            if index in wanted:
                found[index] = rgb
            if index >= max(wanted):
                break
    finally:
        source.close()
    return found


def _read_k_table(path: Path) -> dict | None:
    """``{method: {region: {"ks": [...], "errors": [...]}}}`` from JSON, as (ks, errors) pairs."""
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        return {m: {r: (v["ks"], v["errors"]) for r, v in regions.items()} for m, regions in data.items()}
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise InputError(f"{path}: expected {{method: {{region: {{ks: [...], errors: [...]}}}}}} ({exc})") from None


def write_take_preview(outdir, path=None, *, progress: bool = True, backend: str = "auto",
                       height: int | None = None) -> Path:
    """Render the preview video of an output folder of ``keyshape run``.

    Parameters
    ----------
    outdir : str or Path
        Holds ``take.json``, the track, keys, weights and ``animation.glb``.
    path : str or Path, optional
        Output MP4; default ``outdir / "preview.mp4"``.
    progress, backend, height : keyword-only
        See :func:`keyshape.render.preview.render_preview`.

    Returns
    -------
    Path
    """
    outdir = Path(outdir)
    movie = _preview(outdir, _load_take(outdir), path=path, progress=progress, backend=backend, height=height)
    if movie is None:
        raise InputError(f"{outdir}: no animation.glb to drive the character; run `keyshape run` first")
    return movie


def _preview(outdir: Path, take: _Take, *, path=None, progress: bool, backend: str,
             height: int | None = None) -> Path | None:
    from .io.gltf import read_glb_animation, read_rig
    from .render.preview import render_preview, rotations_from_quaternions

    glb = outdir / take.info["files"].get("animation", "animation.glb")
    if not glb.is_file():
        return None
    rig, animation = read_rig(glb), read_glb_animation(glb)
    order = [animation.names.index(n) for n in rig.names] if animation.names else list(range(rig.n_targets))
    rotations = None if animation.rotations is None else rotations_from_quaternions(animation.rotations)
    return render_preview(take.track, take.weights, rig, path or outdir / "preview.mp4", video=take.video,
                          keys=take.keys, rig_weights=animation.weights[:, order], rotations=rotations,
                          height=height, backend=backend, progress=progress)


def _stable(keys: KeyShapes) -> np.ndarray:
    return keys.stable if keys.stable is not None else stable_points(keys.n_landmarks)
