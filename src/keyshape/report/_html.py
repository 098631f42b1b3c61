"""The take report as one HTML page: :func:`write_report`.

Tables of the numbers (:func:`keyshape.report._fit.take_numbers`), the pictures embedded as
base64 data URIs, the preview video linked beside it (the page says so when it is not there) or
embedded, the key-shape list and how the
numbers are defined; the numbers again as JSON in a ``<script>`` block for tools to read.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

from ..containers import KeyShapes
from ..io.atomic import atomic_path

__all__ = ["write_report"]


def data_uri(path: Path, mime: str) -> str:
    return f"data:{mime};base64," + base64.b64encode(Path(path).read_bytes()).decode("ascii")


_CSS = """
body{font:15px/1.45 system-ui,sans-serif;margin:0 auto;max-width:1180px;padding:18px 24px;color:#1d1f23}
h1{font-size:22px;margin:6px 0 2px} h2{font-size:17px;margin:26px 0 8px;border-bottom:1px solid #ddd}
.sub{color:#666;margin:0 0 12px} table{border-collapse:collapse;margin:6px 0}
td,th{padding:3px 10px;border-bottom:1px solid #eee;text-align:left} th{background:#f5f5f7}
td.n{text-align:right;font-variant-numeric:tabular-nums} img,video{max-width:100%;border:1px solid #ddd}
.note{color:#555;font-size:13px} code{background:#f3f3f5;padding:0 3px}
.missing{background:#fff4d6;border:1px solid #e6c36a;border-radius:4px;padding:10px 14px}
"""


def write_report(path, numbers: dict, keys: KeyShapes, *, title: str, images: dict[str, Path],
                 video: str | None = None, notes: list[str] | None = None, mapping: dict | None = None,
                 descriptions: tuple[str, ...] | None = None) -> Path:
    """Write the HTML report (everything in it but a linked video), atomically.

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
    mapping : dict, optional, keyword-only
        ``{key: {target: gain}}``: the map that drives the rig's own shapes (``map.json``), shown
        as a table under the key shapes.
    descriptions : tuple of n_keys str, optional, keyword-only
        A readable line per key (:func:`keyshape.report.describe_keys`), in the key table and the map.

    Returns
    -------
    Path
    """
    parts = [f"<h1>{html.escape(title)}</h1>", _subtitle(numbers)]
    parts += [f'<p class="note">{html.escape(n)}</p>' for n in notes or []]
    parts += ["<h2>Numbers</h2>", _numbers_table(numbers), _regions_table(numbers), _neutral_note(numbers),
              _hidden_note(numbers)]
    if video:
        parts += ["<h2>Preview</h2>", _video(video),
                  ('<p class="note">Left: the source video with the tracked landmarks (one colour '
                   "per region). Right: the character driven by the same weights and head rotation. "
                   "Bottom: the current key-shape weights.</p>")]
    for caption_text, png in images.items():
        parts += [f"<h2>{html.escape(caption_text)}</h2>",
                  f'<img alt="{html.escape(caption_text)}" src="{data_uri(png, "image/png")}">']
    described = dict(zip(keys.names, descriptions or ()))
    parts += ["<h2>Key shapes</h2>", _keys_table(keys, numbers["fps"], numbers.get("key_frames"), described)]
    if mapping:
        parts += ["<h2>The map: key shapes to the rig's shapes (map.json)</h2>", _map_table(keys, mapping, described)]
    parts += [_definitions(numbers)]
    data = json.dumps(numbers).replace("</", "<\\/")
    document = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
                f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>\n"
                + "\n".join(parts)
                + f'\n<script type="application/json" id="numbers">{data}</script>\n</body></html>\n')
    with atomic_path(path) as tmp:
        tmp.write_text(document, encoding="utf-8")
    return Path(path)


# shows the message (and hides the empty player) when the linked video cannot be loaded
_MISSING_VIDEO_SCRIPT = """<script>(function () {
  var video = document.getElementById('preview'), note = document.getElementById('preview-missing');
  function missing() { video.hidden = true; note.hidden = false; }
  if (video.error) missing();
  video.addEventListener('error', missing);
})();</script>"""


def _video(video: str) -> str:
    """The preview player: embedded (a ``data:`` URI), or linked beside the report with the message
    a reader sees when the file is not there (the page opened on its own, copied or mailed)."""
    player = f'<video id="preview" controls loop muted preload="metadata" src="{html.escape(video)}"></video>'
    if video.startswith("data:"):
        return player
    name = html.escape(video)
    return (player
            + f'<p class="missing" id="preview-missing" hidden><b>The preview video is not here.</b> This page plays '
              f"<code>{name}</code> from its own folder, and there is no <code>{name}</code> beside it: open "
              f"the report in the take's output folder, copy <code>{name}</code> next to it, or write a report "
              f"that carries the video: <code>keyshape report FOLDER --embed-video</code>.</p>"
            + _MISSING_VIDEO_SCRIPT)


def _subtitle(n: dict) -> str:
    return (f'<p class="sub">{n["frames"]} frames at {n["fps"]:g} fps ({n["duration_s"]:g} s) · '
            f'{n["n_keys"]} key shapes ({html.escape(str(n["method"]))}) · neutral frame {n["neutral_frame"]}</p>')


def _neutral_note(n: dict) -> str:
    """The neutral frame: which rule chose it, how sure that is and why."""
    c = n.get("neutral")
    if not c:
        return ""
    rule = {"scores": "the least activated frame by the tracker's expression scores with the whole face in view",
            "median": "the frame nearest the median aligned shape", "given": "given (--neutral)",
            "clip": "from a separate clip (--neutral FILE)"}[c["rule"]]
    return (f'<p class="note" id="neutral">Neutral frame {c["frame"]}: {html.escape(rule)}. Confidence '
            f'<b>{html.escape(c["confidence"])}</b>: {html.escape(c["reason"])}. Pass <code>--neutral FRAME</code> '
            f"to choose another.</p>")


def _hidden_note(n: dict) -> str:
    """Frames whose region was hidden by a hand: no key was taken there and the solve
    leaned on the smoothness across them."""
    hidden = {r: v for r, v in (n.get("hidden") or {}).items() if v["frames"]}
    if not hidden:
        return ('<p class="note" id="hidden">Hidden: no frame. No hand was found over the face, so every '
                "landmark of every frame counts as seen.</p>")
    text = ", ".join(f'{html.escape(r)} {v["frames"]} frames ({100 * v["share"]:.0f} %)' for r, v in hidden.items())
    return (f'<p class="note" id="hidden">Hidden by a hand (MediaPipe\'s hand landmarker found one covering more '
            f"than 30 % of the region's landmarks): {text}. "
            "No key comes from these frames; the solve leaves the covered landmarks out and "
            "bridges fully hidden spans with the smoothness term (shaded in the weights plot).</p>")


def _neutral_frame(n: dict) -> str:
    """The neutral's frame of the take (what ``--neutral`` takes), and the video's own number when
    the take starts later (``--start``)."""
    at = n.get("neutral_video_frame")
    shown = str(n["neutral_frame"])
    return shown + (f' (video frame {at["frame"]})' if at and at["frame"] != n["neutral_frame"] else "")


def _numbers_table(n: dict) -> str:
    rows = [("frames", n["frames"]), ("frames with a face", n["frames_with_face"]),
            ("detection rate", f'{n["detection_rate"]:.2f} %'), ("gaps (runs of frames without a face)", n["gaps"]),
            ("longest gap", f'{n["longest_gap_frames"]} frames ({n["longest_gap_s"]:g} s)'),
            ("neutral frame", _neutral_frame(n)), ("key shapes in all", n["n_keys"])]
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


def _keys_table(keys: KeyShapes, fps: float, video_frames=None, described: dict | None = None) -> str:
    """One row per key: what it looks like (``described``: key -> line), its frame and time in the
    video (``video_frames``, from :func:`take_numbers`; the track row over ``fps`` for a key of another take)."""
    video_frames = video_frames or [None] * keys.n_keys
    described = described or {}
    when = [(at["frame"], at["time"]) if at else (int(f), f / fps) for at, f in zip(video_frames, keys.frames)]
    rows = "".join(f'<tr data-key="{html.escape(keys.names[k])}"><td>{html.escape(keys.names[k])}</td>'
                   f'<td class="what">{html.escape(described.get(keys.names[k], ""))}</td>'
                   f"<td>{html.escape(keys.key_regions[k])}</td>"
                   f'<td class="n">{when[k][0]}</td><td class="n">{when[k][1]:.2f} s</td>'
                   f"<td>{html.escape(keys.takes[k])}</td></tr>" for k in range(keys.n_keys))
    return ('<table id="keys"><tr><th>name</th><th>what it is (region; the ARKit expressions MediaPipe scored '
            "highest at its frame, as the rise from the neutral)</th><th>region</th><th>video frame</th>"
            f"<th>time</th><th>take</th></tr>{rows}</table>")


def _map_table(keys: KeyShapes, mapping: dict, described: dict | None = None, shown: int = 6) -> str:
    """One row per key (and what it is, ``described``): the rig's shapes it drives, strongest first
    (``shown`` of them), with their gains."""
    described, rows = described or {}, []
    for name in [*keys.names, *(k for k in mapping if k not in keys.names)]:
        drives = sorted(((g, t) for t, g in mapping.get(name, {}).items() if g > 0), reverse=True)
        terms = ", ".join(f"{html.escape(t)} ×{g:.2f}" for g, t in drives[:shown])
        if len(drives) > shown:
            terms += f", … ({len(drives) - shown} more)"
        rows.append(f'<tr data-key="{html.escape(name)}"><td>{html.escape(name)}</td>'
                    f'<td class="what">{html.escape(described.get(name, ""))}</td>'
                    f"<td>{terms or '<i>none</i>'}</td></tr>")
    return ('<table id="map"><tr><th>key shape</th><th>what it is</th><th>drives the rig\'s shapes (gain: the '
            f"shape's weight at the key's full weight)</th></tr>{''.join(rows)}</table>")


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
