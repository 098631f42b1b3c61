"""What a take found and how well it fits: numbers, pictures, preview, in one ``report.html``.

:func:`write_take_extras` turns an output folder of ``keyshape run`` (``take.json``,
``track.npz``, ``keys.json``, ``weights.csv``, ``animation.glb``) into ``preview.mp4``,
``keyshapes.png``, ``weights.png`` (and ``error_vs_k.png`` when a table is given) and a
self-contained ``report.html``: pictures embedded as data URIs, no network needed.

This module reads the take folder and puts the pieces together. Fit quality
(:func:`fit_quality`: the error per frame and region, the cost of w ≥ 0, frames outside
the key-shape hull) and the report's numbers are defined in :mod:`keyshape.report._fit`;
the HTML page is written by :func:`write_report` (:mod:`keyshape.report._html`). Both are
re-exported here.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..containers import KeyShapes, Track, Weights
from ..exceptions import InputError
from ..schemes import stable_points
from ._describe import describe_keys
from ._fit import HULL_TOLERANCE, FitQuality, face_scale, fit_quality, gap_runs, take_numbers
from ._html import data_uri, write_report
from ._neutral import neutral_picture, separate_neutral

__all__ = ["FitQuality", "fit_quality", "face_scale", "gap_runs", "take_numbers", "write_report",
           "write_take_extras", "write_take_preview", "TakeExtras", "HULL_TOLERANCE"]


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
        Renderer for the preview (see :func:`keyshape.render._backend.make_renderer`).
    k_table : dict, optional, keyword-only
        Error against K, ``{method: {region: (ks, errors)}}`` (see :func:`keyshape.report.plots.error_vs_k`),
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
    numbers = take_numbers(take.track, take.keys, fit, take=take.name)
    pictures = _pictures(outdir, take, fit, k_table)
    notes = [] if take.video is not None else [(f"The source video {take.info.get('video')!r} was not found: "
                                                "landmarks are drawn on a blank background.")]
    quality = _correspondence_quality(outdir / "correspondence.json")
    if quality:
        numbers["correspondence"] = quality
        notes.append(f"Correspondence found on a render of the character: {quality['landmarks_kept']} of "
                     f"{quality['of']} landmarks on its surface, {quality['moved']} moved onto a usable part; "
                     f"median {quality['median_residual_pct']:g} %, 95 % within {quality['p95_residual_pct']:g} % "
                     "of the render's width from where MediaPipe put them (check correspondence.json if large).")
    refined = _refinement(outdir / "map.json")
    if refined:
        numbers["render_and_compare"] = refined
        notes.append(_refinement_note(refined))
    movie = _preview(outdir, take, progress=progress, backend=backend) if preview else None
    if not preview and (outdir / "preview.mp4").is_file():
        movie = outdir / "preview.mp4"  # from an earlier run
    if preview and movie is None:
        notes.append(f"No preview: {take.info['files'].get('animation', 'animation.glb')} is missing.")
    gains = _map_gains(outdir / "map.json")
    captions = {**_CAPTIONS, "keyshapes": _MAPPED_KEYS_CAPTION} if gains else _CAPTIONS
    with tempfile.TemporaryDirectory(prefix="keyshape-report-") as work:
        curves = _rig_curves(outdir, take, Path(work)) if gains else None
        images = {captions[k]: p for k, p in {**pictures, **({"rig": curves} if curves else {})}.items()}
        report = write_report(outdir / "report.html", numbers, take.keys, title=f"keyshape · {take.name}",
                              images=images, video=_video_source(movie, embed_video), notes=notes, mapping=gains,
                              descriptions=_descriptions(take))
    return TakeExtras(report, movie, pictures, numbers)


def _names(take: _Take) -> tuple[str, str]:
    """The names ``keys.takes`` may give this take: the video's and the track file's."""
    return take.name, take.info.get("files", {}).get("track", "track.npz")


def _descriptions(take: _Take) -> tuple[str, ...]:
    return describe_keys(take.keys, take.track, take=_names(take), weights=take.weights)


def _entry(path: Path, key: str):
    """``key`` of the JSON object in ``path``; None when the file is missing or not such an object."""
    import json

    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8")).get(key)
    except (OSError, ValueError, AttributeError):
        return None


def _correspondence_quality(path: Path) -> dict | None:
    """The ``quality`` of an automatic correspondence file beside the take (None without one)."""
    quality = _entry(path, "quality")
    needed = ("landmarks_kept", "of", "moved", "median_residual_pct", "p95_residual_pct")
    return quality if isinstance(quality, dict) and all(k in quality for k in needed) else None


def _refinement(path: Path) -> dict | None:
    """The ``refined`` entry of the automatic ``map.json`` beside the take (None without one)."""
    refined = _entry(path, "refined")
    return refined if isinstance(refined, dict) and isinstance(refined.get("targets"), list) else None


def _refinement_note(refined: dict) -> str:
    if not refined["targets"]:
        skipped = refined.get("skipped", "no reason given")
        return f"Render and compare skipped ({skipped}): every target follows the scores."
    before, after = refined.get("residual_px", (float("nan"), float("nan")))
    return (f"Render and compare refined {', '.join(refined['targets'])} on the landmarks of the character's own "
            f"renders: landmark residual {before:.2f} px → {after:.2f} px (RMS, video pixels).")


def _video_source(movie: Path | None, embed: bool) -> str | None:
    if movie is None:
        return None
    return data_uri(movie, "video/mp4") if embed else movie.name


_CAPTIONS = {"keyshapes": "Key shapes: the sculpt list", "weights": "Weights over time and fit error",
             "error_vs_k": "Error against the number of key shapes",
             "rig": "The rig's own shapes over time (animation.glb)"}
_MAPPED_KEYS_CAPTION = "Key shapes: what map.json turns into the rig's own shapes"


def _map_gains(path: Path) -> dict | None:
    """``{key: {target: gain}}`` of the ``map.json`` beside the take (wrapped or plain); None without one."""
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    gains = data.get("gains") if isinstance(data, dict) and "gains" in data else data
    if not isinstance(gains, dict) or not all(isinstance(v, dict) for v in gains.values()):
        return None
    return {str(k): {str(t): float(g) for t, g in v.items()} for k, v in gains.items()}


def _rig_curves(outdir: Path, take: _Take, folder: Path) -> Path | None:
    """The picture of the rig's own target weights over time, from ``animation.glb`` (None when it
    names the keys themselves: the built-in character, shown by the weights plot already)."""
    from ..io.gltf import read_glb_animation
    from . import plots

    path = outdir / take.info.get("files", {}).get("animation", "animation.glb")
    if not path.is_file():
        return None
    animation = read_glb_animation(path)
    if set(animation.names) <= set(take.keys.names) | {n for n in animation.names if n.startswith("eyeLook")}:
        return None
    rig = Weights(np.asarray(animation.weights, dtype=float), tuple(animation.names), take.weights.fps)
    return plots.rig_curves(rig, folder / "rig.png")


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
    from ..alignment import align
    from ..io.gltf import check_gltf_file
    from ..io.keys_json import load_keys
    from ..io.take import load_take_info, take_video
    from ..io.track import load_track
    from ..io.weights_csv import load_weights_csv

    info = load_take_info(outdir)
    files = info.get("files") or {}
    animation = outdir / files.get("animation", "animation.glb")
    if animation.is_file():
        check_gltf_file(animation)  # a damaged one is said even when no preview is made
    track = load_track(outdir / files.get("track", "track.npz"))
    keys = load_keys(outdir / files.get("keys", "keys.json"))
    weights = load_weights_csv(outdir / files.get("weights", "weights.csv"))
    if weights.n_frames != track.n_frames:
        raise InputError(f"{outdir}: the weights have {weights.n_frames} frames but the track has {track.n_frames}")
    aligned, _ = align(track, reference=keys.neutral, stable=_stable(keys))
    video = take_video(outdir, info)  # a gone video is said, once
    name = Path(info["video"]).name if info.get("video") else outdir.name
    return _Take(info, name, video, track, keys, weights, aligned)


def _pictures(outdir: Path, take: _Take, fit: FitQuality, k_table) -> dict[str, Path]:
    from . import plots

    frames = [f for f in [int(take.keys.neutral_frame), *take.keys.frames.tolist()] if f < take.track.n_frames]
    source = take.track.frame_index  # track row -> the video's frame number
    found = _read_frames(take.video, [int(source[f]) for f in frames])
    images = {f: found[int(source[f])] for f in frames if int(source[f]) in found}
    out = {"keyshapes": plots.contact_sheet(take.keys, take.track, images, outdir / "keyshapes.png",
                                            take=_names(take), neutral=_neutral_picture(take),
                                            descriptions=_descriptions(take)),
           "weights": plots.weight_curves(take.weights, take.keys, fit, outdir / "weights.png",
                                            hidden=_hidden(take))}
    k_table = k_table if k_table is not None else _read_k_table(outdir / "error_vs_k.json")
    if k_table:
        chosen = {r: len(take.keys.keys_of(r)) for r in take.keys.regions}
        out["error_vs_k"] = plots.error_vs_k(k_table, outdir / "error_vs_k.png", unit=fit.unit, chosen=chosen)
    return out


def _read_frames(video: Path | None, frames: list[int]) -> dict[int, np.ndarray]:
    """The video frames with the given indices (none without a video)."""
    if video is None or not frames:
        return {}
    from ..capture.video import iter_frames

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
    from ..io.gltf import read_glb_animation, read_head_motion
    from ..io.validate import check_glb
    from ..render.preview import render_preview

    glb = outdir / take.info["files"].get("animation", "animation.glb")
    if not glb.is_file():
        return None
    check_glb(glb)
    try:
        (rig, colours), animation, motion = _face_scene(glb), read_glb_animation(glb), read_head_motion(glb)
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{glb}: a damaged .glb ({exc.__class__.__name__}: {exc})") from None
    order = [animation.names.index(n) for n in rig.names] if animation.names else list(range(rig.n_targets))
    pivot, rotations = (None, None) if motion is None else motion
    return render_preview(take.track, take.weights, rig, path or outdir / "preview.mp4", video=take.video,
                          keys=take.keys, rig_weights=animation.weights[:, order], rotations=rotations,
                          height=height, backend=backend, progress=progress, colours=colours, pivot=pivot)


def _face_scene(glb: Path) -> tuple:
    """The character's face as the preview draws it: a rig (the morph meshes and the still ones
    about them, such as the hair) and its sRGB colours ``(n_vertices, 3)`` (textures sampled at
    the vertices; ``COLOR_0``, which glTF stores linear, encoded)."""
    from ..io.gltf import load_document, read_face_scene

    document, _ = load_document(glb, editable=False)
    rig, rgba = read_face_scene(glb)
    colours = rgba[:, :3]
    if any(getattr(p.attributes, "COLOR_0", None) is not None for m in document.meshes for p in m.primitives):
        colours = np.where(colours <= 0.0031308, 12.92 * colours, 1.055 * np.clip(colours, 0, 1) ** (1 / 2.4) - 0.055)
    return rig, colours


def _neutral_picture(take: _Take):
    """The neutral's own picture and landmarks when it comes from a file (``--neutral FILE``), else None."""
    source = take.info.get("neutral_source")
    if not source or not separate_neutral(take.keys):
        return None
    return neutral_picture(source, int(take.keys.neutral_frame))


def _hidden(take: _Take) -> dict[str, np.ndarray] | None:
    """Per region, (n_frames,) bool: frames whose region is hidden (as key discovery counts it)."""
    if take.track.visibility is None or take.track.n_frames != take.weights.n_frames:
        return None
    return {r: (take.track.visibility[:, ix] < 0.5).mean(axis=1) > 0.3 for r, ix in take.keys.regions.items()}


def _stable(keys: KeyShapes) -> np.ndarray:
    return keys.stable if keys.stable is not None else stable_points(keys.n_landmarks)
