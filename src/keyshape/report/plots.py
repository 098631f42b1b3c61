"""Pictures of a take: the key-shape contact sheet, weight curves with the fit error, error vs K.

The only module that imports matplotlib, always through the non-interactive Agg canvas
(no pyplot, no display, no global state). Every function writes one PNG atomically and
returns its path; the data come in as arrays and core types, never read from files here.
"""

from __future__ import annotations

import textwrap
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..containers import KeyShapes, Track, Weights
from ..exceptions import InputError, MissingDependencyError
from ..io.atomic import atomic_path
from ..render.draw import OTHER_COLOUR, region_palette

if TYPE_CHECKING:
    from ._take import FitQuality

__all__ = ["contact_sheet", "weight_curves", "rig_curves", "error_vs_k"]

_GAP_COLOUR = "#9a9a9a"
_KEY_COLOURS = ("#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#66a61e", "#e6ab02", "#a6761d", "#666666",
                "#1f78b4", "#b2df8a", "#fb9a99", "#cab2d6")


def _figure(width: float, height: float):
    """A matplotlib Figure on an Agg canvas."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise MissingDependencyError("matplotlib") from None
    figure = Figure(figsize=(width, height), dpi=100, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _save(figure, path) -> Path:
    with atomic_path(path) as tmp:
        figure.savefig(tmp, format="png", dpi=100, facecolor="white")
    return Path(path)


def _rgb(colour) -> tuple[float, float, float]:
    return tuple(c / 255 for c in colour)


# --------------------------------------------------------------------------- contact sheet


def contact_sheet(keys: KeyShapes, track: Track, images: Mapping[int, np.ndarray], path, *,
                  take: str | tuple[str, ...] = "", columns: int = 6,
                  neutral: tuple[np.ndarray, np.ndarray] | None = None,
                  descriptions: tuple[str, ...] | None = None) -> Path:
    """The "sculpt list": the neutral frame and every key frame, cropped around the face.

    Each tile shows the frame with its landmarks, the key's region highlighted in the
    region's colour, titled with the key name and source frame; a mirrored key shows its
    source's frame flipped left to right (what the mirrored key is). Keys from another take
    (``keys.takes[k]`` not in ``("", take)``) and frames without a picture are drawn as the
    key shape's landmarks alone.

    Parameters
    ----------
    keys : KeyShapes
    track : Track
        The take, in image pixels (``points (n_frames, n_landmarks, 2 or 3)``).
    images : mapping int -> (height, width, 3) uint8
        Video frames by frame index (those of ``keys.frames`` and ``keys.neutral_frame``).
    path : str or Path
        Output PNG.
    take : str or tuple of str, keyword-only
        Name(s) of this take as recorded in ``keys.takes`` (e.g. the video's or the track's file name).
    columns : int, keyword-only
    neutral : (rgb, points), optional, keyword-only
        The picture ``(height, width, 3) uint8`` and landmarks ``(n_landmarks, 2)`` of a neutral
        from a file of its own (``keys.neutral_take``, see :func:`keyshape.report._neutral.neutral_picture`):
        its tile shows them, titled with the file's name.
    descriptions : tuple of n_keys str, optional, keyword-only
        A readable line per key (:func:`keyshape.report.describe_keys`), printed under its tile's title.

    Returns
    -------
    Path
    """
    tiles = [("neutral", None, int(keys.neutral_frame), keys.neutral_take)]
    tiles += [(keys.names[k], keys.key_regions[k], int(keys.frames[k]), keys.takes[k]) for k in range(keys.n_keys)]
    columns = max(1, min(columns, len(tiles)))
    rows = -(-len(tiles) // columns)
    figure = _figure(2.3 * columns, (3.05 if descriptions else 2.55) * rows)
    axes = figure.subplots(rows, columns, squeeze=False).ravel()
    palette = region_palette(keys.regions)
    ours = {"", *((take,) if isinstance(take, str) else take)}
    for ax, (name, region, frame, source) in zip(axes, tiles):
        own = source in ours and 0 <= frame < track.n_frames and track.valid[frame]
        key = None if region is None else keys.names.index(name)
        if key is None and neutral is not None and not own and np.isfinite(neutral[1]).all():  # --neutral FILE
            _tile(ax, keys, None, neutral[1], neutral[0], palette)
        else:
            _tile(ax, keys, key, track.points[frame] if own else None, images.get(frame) if own else None,
                  palette)
        title = f"{name} · frame {frame}" if own else f"{name} · {source or 'take'} #{frame}"
        if key is not None and keys.mirror_of[key]:  # drawn as it is: the source frame, flipped
            ax.set_xlim(*ax.get_xlim()[::-1])
            title = f"{name} · mirrored {frame}"
        ax.set_title(title, fontsize=9, color=_rgb(palette[region]) if region else "black")
        if key is not None and descriptions:  # what the key is, under its picture
            ax.set_xlabel(textwrap.fill(descriptions[key], 36), fontsize=7, color="#333333", linespacing=1.1)
    for ax in axes[len(tiles):]:
        ax.set_axis_off()
    return _save(figure, path)


def _tile(ax, keys: KeyShapes, key: int | None, points: np.ndarray | None, image, palette) -> None:
    """One contact-sheet tile: a face crop with landmarks (or the key shape's landmarks)."""
    ax.set_xticks([])
    ax.set_yticks([])
    if points is None:
        points = keys.neutral if key is None else keys.neutral + keys.deltas[key]
        image = None
    xy = points[:, :2]
    x0, y0, x1, y1 = _square_box(xy, None if image is None else image.shape[:2])
    ax.set_facecolor("#202226")
    if image is not None:
        ax.imshow(image, interpolation="bilinear")
    colours = np.tile(np.array(_rgb(OTHER_COLOUR)), (len(xy), 1))
    sizes = np.full(len(xy), 0.6)
    if key is not None:
        region = keys.key_regions[key]
        lm = keys.regions[region]
        colours[lm], sizes[lm] = _rgb(palette[region]), 3.0
    ax.scatter(xy[:, 0], xy[:, 1], s=sizes, c=colours, linewidths=0)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1, y0)  # image rows grow downward
    ax.set_aspect("equal")


def _square_box(xy: np.ndarray, shape=None, *, margin: float = 0.12) -> tuple[float, float, float, float]:
    """A square (x0, y0, x1, y1) around the points, ``margin`` of their size on each side.

    With an image ``shape (height, width)`` the square is moved (and shrunk if needed) to
    stay inside the image.
    """
    lo, hi = np.nanmin(xy, axis=0), np.nanmax(xy, axis=0)
    centre, half = (lo + hi) / 2, max(np.max(hi - lo) / 2, 1e-6) * (1 + 2 * margin)
    if shape is not None:
        size = np.array([shape[1], shape[0]], dtype=float)
        half = min(half, size.min() / 2)
        centre = np.clip(centre, half, size - half)
    return centre[0] - half, centre[1] - half, centre[0] + half, centre[1] + half


# --------------------------------------------------------------------------- weight curves


def weight_curves(weights: Weights, keys: KeyShapes, fit: FitQuality, path, *,
                  hidden: dict[str, np.ndarray] | None = None) -> Path:
    """Weights over time, one panel per region, with the reconstruction error underneath.

    Frames without a face are shaded grey; frames outside a region's key-shape hull
    (``fit.outside``, see :func:`keyshape.report._take.fit_quality`) are shaded in the region's colour;
    frames where the region is hidden (``hidden[region]``, (n_frames,) bool: a hand over the mouth)
    are hatched. Each key of a region has a colour of its own (a mirrored key's line dashed); each
    panel's legend names its keys, then what its shaded and hatched spans mean.

    Parameters
    ----------
    weights : Weights
        ``values (n_frames, n_keys)`` named after ``keys.names``.
    keys : KeyShapes
    fit : FitQuality
        Per-region ``error``, ``excess`` and ``outside`` arrays ``(n_frames,)``, ``unit`` and
        ``tolerance``.
    path : str or Path
        Output PNG.

    Returns
    -------
    Path
    """
    return _save(_weight_figure(weights, keys, fit, hidden), path)


def _weight_figure(weights: Weights, keys: KeyShapes, fit: FitQuality, hidden):
    """The figure :func:`weight_curves` saves."""
    regions = list(keys.regions)
    times = weights.times
    figure = _figure(12, 2.0 * len(regions) + 2.6)
    axes = figure.subplots(len(regions) + 1, 1, sharex=True,
                           gridspec_kw={"height_ratios": [1.0] * len(regions) + [1.2]})
    palette = region_palette(regions)
    gaps = ~np.isfinite(weights.values).all(axis=1)
    for ax, region in zip(axes, regions):
        _region_panel(ax, weights, keys, region, palette[region])
        spans = []
        if gaps.any():
            _shade(ax, times, gaps, _GAP_COLOUR, 0.35)
            spans.append(_patch(facecolor=_GAP_COLOUR, alpha=0.35, label="no face"))
        if np.any(fit.outside[region]):
            _shade(ax, times, fit.outside[region], _rgb(palette[region]), 0.18)
            spans.append(_patch(facecolor=_rgb(palette[region]), alpha=0.18, label="outside the key-shape hull"))
        if hidden is not None and np.any(hidden.get(region, False)):
            _hatch(ax, times, np.asarray(hidden[region], dtype=bool))
            spans.append(_patch(facecolor="none", edgecolor="0.35", hatch="//", lw=0.0,
                                label=f"{region} hidden: weights bridged"))
        _legend(ax, spans)
    _error_panel(axes[-1], times, fit, palette)
    _shade(axes[-1], times, gaps, _GAP_COLOUR, 0.35)
    axes[-1].set_xlabel("time (s)")
    axes[-1].set_xlim(times[0] if len(times) else 0, times[-1] if len(times) > 1 else 1)
    return figure


def key_colours(n: int) -> list[str]:
    """``n`` line colours, all different for ``n`` up to 52 (then they repeat): :data:`_KEY_COLOURS`, then
    the tab20b and tab20c colours.

    >>> len(set(key_colours(40)))
    40
    """
    from matplotlib import colormaps
    from matplotlib.colors import to_hex

    extra = [to_hex(c) for name in ("tab20b", "tab20c") for c in colormaps[name].colors]
    colours = list(dict.fromkeys([*_KEY_COLOURS, *extra]))
    return [colours[i % len(colours)] for i in range(n)]


def _patch(**style):
    from matplotlib.patches import Patch

    return Patch(**style)


def _legend(ax, spans: list) -> None:
    """The panel's legend: its keys' lines, then what its shaded and hatched spans mean."""
    lines, labels = ax.get_legend_handles_labels()
    handles = [*lines, *spans]
    if handles:
        ax.legend(handles=handles, labels=[*labels, *(s.get_label() for s in spans)], loc="upper left",
                  bbox_to_anchor=(1.0, 1.0), fontsize=7, frameon=False)


def _region_panel(ax, weights: Weights, keys: KeyShapes, region: str, colour) -> None:
    """One line per key of ``region``, each its own colour; a mirrored key dashed."""
    members = [weights.names.index(keys.names[k]) for k in keys.keys_of(region)
               if keys.names[k] in weights.names]
    for channel, line_colour in zip(members, key_colours(len(members))):
        name = weights.names[channel]
        ax.plot(weights.times, weights.values[:, channel], lw=1.0, color=line_colour, label=name,
                ls="--" if name.endswith("_mirror") else "-")
    ax.set_ylabel(f"{region}\nweight", color=_rgb(colour))
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.25)


def _error_panel(ax, times: np.ndarray, fit: FitQuality, palette) -> None:
    for region, colour in palette.items():
        ax.plot(times, fit.error[region], lw=1.0, color=_rgb(colour), label=f"{region} error")
        ax.plot(times, fit.excess[region], lw=0.8, ls=":", color=_rgb(colour),
                label=f"{region} cost of w ≥ 0")
        out = np.asarray(fit.outside[region], dtype=bool)
        ax.plot(times[out], fit.excess[region][out], ls="none", marker="v", ms=3, color=_rgb(colour),
                label=f"{region} outside the hull ({int(out.sum())})")
    ax.axhline(fit.tolerance, color="black", lw=0.8, ls="--", label="hull tolerance")
    ax.set_ylabel(f"RMS error\n({fit.unit})")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.25)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=7, frameon=False)


def _hatch(ax, times: np.ndarray, mask: np.ndarray) -> None:
    """Hatch the runs of ``mask`` (a hidden region: its weights are the smoothness term's bridge)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    for start, stop in zip(edges[::2], edges[1::2]):
        ax.axvspan(times[start], times[stop - 1], facecolor="none", edgecolor="0.35", hatch="//", lw=0.0)


def _shade(ax, times: np.ndarray, mask: np.ndarray, colour, alpha: float) -> None:
    """Shade the time spans of the runs of True in ``mask`` (each frame spans 1/fps)."""
    if len(times) < 2:
        return
    step = times[1] - times[0]
    for start, stop in _runs(np.asarray(mask, dtype=bool)):
        ax.axvspan(times[start] - step / 2, times[stop - 1] + step / 2, color=colour, alpha=alpha, lw=0)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of every run of True.

    Examples
    --------
    >>> _runs(np.array([0, 1, 1, 0, 1], bool))
    [(1, 3), (4, 5)]
    """
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def rig_curves(weights: Weights, path, *, shown: int = 12) -> Path:
    """The rig's own target weights over time (``jawOpen``, ``mouthSmile_L``, ...): the ``shown``
    most active (largest range over the take), each its own colour, named in the legend.

    ``weights``: ``values (n_frames, n_targets)`` named by the rig's targets.
    """
    values = np.nan_to_num(np.asarray(weights.values, dtype=float))
    spread = values.max(axis=0) - values.min(axis=0) if len(values) else np.zeros(len(weights.names))
    order = [int(t) for t in np.argsort(-spread, kind="stable")[:shown] if spread[t] > 0]
    figure = _figure(12, 3.2)
    ax = figure.subplots()
    for t, colour in zip(order, key_colours(len(order))):
        ax.plot(weights.times, values[:, t], lw=1.0, color=colour, label=weights.names[t])
    ax.set_ylabel("rig shape\nweight")
    ax.set_xlabel("time (s)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.25)
    rest = len(weights.names) - len(order)
    ax.set_title(f"the {len(order)} most active of the rig's {len(weights.names)} shapes"
                 + (f" ({rest} move less or not at all)" if rest else ""), fontsize=9, loc="left")
    if order:
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=7, frameon=False)
    return _save(figure, path)


# --------------------------------------------------------------------------- error vs K


def error_vs_k(table: Mapping, path, *, unit: str = "% inter-ocular", chosen: Mapping[str, int] | None = None) -> Path:
    """Reconstruction error against the number of key shapes K, one panel per region.

    Parameters
    ----------
    table : mapping method -> (mapping region -> (ks, errors)) or method -> (ks, errors)
        ``ks (n,) int`` and ``errors (n,) float`` per method and region; a bare pair is one
        region called ``"whole"``.
    path : str or Path
        Output PNG.
    unit : str, keyword-only
        Unit of the errors, for the axis label.
    chosen : mapping region -> int, optional, keyword-only
        The K in use, marked with a vertical line.

    Returns
    -------
    Path
    """
    by_region = _regroup(table)
    figure = _figure(4.2 * len(by_region), 3.4)
    axes = np.atleast_1d(figure.subplots(1, len(by_region), squeeze=False).ravel())
    for ax, (region, curves) in zip(axes, by_region.items()):
        for method, (ks, errors) in curves.items():
            ax.plot(ks, errors, marker="o", ms=3, lw=1.2, label=method)
        if chosen and region in chosen:
            ax.axvline(chosen[region], color="black", lw=0.8, ls="--")
        ax.set_title(region, fontsize=10)
        ax.set_xlabel("key shapes K")
        ax.set_ylabel(f"RMS error ({unit})")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.25)
        ax.legend(fontsize=8, frameon=False)
    return _save(figure, path)


def _regroup(table: Mapping) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """region -> method -> (ks, errors), validated."""
    if not table:
        raise InputError("error_vs_k needs at least one method; got an empty table")
    out: dict[str, dict] = {}
    for method, entry in table.items():
        per_region = entry if isinstance(entry, Mapping) else {"whole": entry}
        for region, pair in per_region.items():
            ks, errors = (np.asarray(a, dtype=float).ravel() for a in pair)
            if ks.shape != errors.shape or ks.size == 0:
                raise InputError(f"error_vs_k: {method}/{region} needs as many errors as ks (at least one); "
                                 f"got {ks.size} ks and {errors.size} errors")
            out.setdefault(str(region), {})[str(method)] = (ks, errors)
    return out


# --------------------------------------------------------------------------- coverage of a new take


def coverage(errors: Mapping[str, np.ndarray], max_error: float, added: Mapping[str, list[float]], times: np.ndarray,
             path, *, unit: str = "% inter-ocular") -> Path:
    """How well a key set reaches a take: per region the error over time, and the error against
    keys added from the take (what ``keys --extend`` would add).

    Parameters
    ----------
    errors : mapping region -> (n_frames,) float, each frame's RMS error of its best blend (NaN: no face)
    max_error : float, the error target (frames above it are out of reach, shaded)
    added : mapping region -> list of float, the take's RMS error with 0, 1, 2, … of its frames added
    times : (n_frames,) float, seconds
    path : str or Path, output PNG

    Returns
    -------
    Path
    """
    regions = list(errors)
    palette = region_palette(regions)
    figure = _figure(13, 2.2 * len(regions) + 0.6)
    grid = figure.add_gridspec(len(regions), 2, width_ratios=[4.0, 1.2])
    for row, region in enumerate(regions):
        colour = _rgb(palette[region])
        ax = figure.add_subplot(grid[row, 0])
        e = np.asarray(errors[region], dtype=float)
        far = np.nan_to_num(e) > max_error
        ax.plot(times, e, lw=0.9, color=colour, label=f"{region}: RMS error per frame")
        ax.axhline(max_error, color="black", lw=0.8, ls="--", label=f"target {max_error:g}")
        _shade(ax, times, far, colour, 0.22)
        _shade(ax, times, ~np.isfinite(e), _GAP_COLOUR, 0.35)
        ax.set_ylabel(f"{region}\n({unit})")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.25)
        share = 100 * far.sum() / max(int(np.isfinite(e).sum()), 1)
        ax.set_title(f"{region}: {int(far.sum())} frames out of reach ({share:.1f} %)", fontsize=9, loc="left")
        ax.legend(loc="upper right", fontsize=7, frameon=False)
        if row == len(regions) - 1:
            ax.set_xlabel("time (s)")
        curve = figure.add_subplot(grid[row, 1])
        values = list(added[region])
        curve.plot(range(len(values)), values, marker="o", ms=3, color=colour)
        curve.axhline(max_error, color="black", lw=0.8, ls="--")
        curve.set_xlim(-0.4, max(len(values) - 1, 1) + 0.4)
        curve.xaxis.get_major_locator().set_params(integer=True)
        curve.set_ylim(bottom=0)
        curve.set_xlabel("keys added from this take", fontsize=8)
        curve.set_ylabel(f"take's RMS error ({unit})", fontsize=8)
        curve.grid(alpha=0.25)
    return _save(figure, path)
