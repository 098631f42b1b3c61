"""Render-and-compare on landmarks for the targets MediaPipe's scores do not see (issue 13, a probe).

Run after ``bench_rendered_loop.py --out DIR`` and on its outputs:

    python benchmarks/bench_rendered_loop.py --out /tmp/loop
    python benchmarks/probe_render_compare.py --out /tmp/loop

The automatic route reads each ARKit target off MediaPipe's score of it. On ICT's renders some
scores barely move with their target, in context (a render at the route's own pose against one
with the target raised by ``δ``): ``jawOpen`` 0.06 per unit weight, ``mouthLowerDown`` 0.00,
``eyeSquint`` 0.04, where the smiles read 0.3. Those targets are invisible to the scores, but not to
the landmarks. This probe renders the character at the route's per-frame weights ``P(t)`` (the
run's ``animation.glb``) and at ``P(t) + δ e_j`` for each probed target ``j``, tracks every render
with the real MediaPipe, and solves per frame

.. math::

    \\min_{\\Delta, \\omega} \\lVert r(t) - J(t) \\Delta - R(t) \\omega \\rVert^2 + \\lambda \\lVert \\Delta \\rVert^2
    + \\mu \\lVert \\omega \\rVert^2, \\qquad 0 \\le P_j(t) + \\Delta_j \\le 1,

where ``r(t)`` is the video's 2-D landmarks less the render's at ``P(t)`` (the renders put onto the
video's picture by one similarity for the whole take), ``J(t)`` the landmarks' response to each
target and ``R(t)`` their response to a small move, scale, roll, pitch and yaw of the head (pitch
and yaw from the render's own depths), which absorbs the error of the head pose the render was
turned by. The refined weights are smoothed
over time (Gaussian, ``--smooth`` frames), then fitted through the key weights (a constant and a
gain per key, ridge 1e-3 per frame, as ``_take_mapping`` fits the scores), which is what a
``map.json`` could carry.

The render is made as the product could make it: the head turned by the rotations MediaPipe
reports for the *video* (``--rotation tracked``), the camera framed on the corresponded points
(``--camera product``). ``--rotation truth --camera video`` renders exactly as the benchmark made its
video, an upper bound no real take allows (a real actor is not a render).

Not part of the product: the measurement behind BENCHMARKS.md's "render and compare" table.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_closed_loop import FACE_AREA, landmark_vertices
from bench_rendered_loop import (
    caricature,
    head_rotations,
    ict_colours,
    rendered_faces,
    truth_from_scores,
    vertex_error,
    vertex_sets,
)

PROBED = ("jawOpen", "mouthLowerDown_L", "mouthLowerDown_R", "eyeSquint_L", "eyeSquint_R",
          "browOuterUp_L", "browOuterUp_R", "mouthPucker")


def render_and_track(rig, colours, weights: np.ndarray, rotations: np.ndarray, camera, pivot: np.ndarray,
                     fps: float, path: Path):
    """The rig posed by ``weights (n_frames, n_targets)``, turned by ``rotations`` about ``pivot``,
    rendered to an MP4 and tracked by MediaPipe: the :class:`~keyshape.containers.Track`."""
    from keyshape.capture import track_video
    from keyshape.render import make_renderer
    from keyshape.render.encode import VideoWriter

    faces = rendered_faces(rig.faces)
    with make_renderer(faces, 512, 512, n_vertices=rig.n_vertices, backend="gl", colours=colours) as renderer, \
            VideoWriter(path, 512, 512, fps, crf=16) as out:
        for f in range(len(weights)):
            posed = rig.pose(weights[f : f + 1])[0]
            out.write(renderer.render((posed - pivot) @ rotations[f].T + pivot, camera))
    return track_video(path, progress=False)


def refine(video, base, raised: dict, route: np.ndarray, names, *, delta: float, ridge: float,
           turn: float, reference: str = "none", neutral: int = 0) -> np.ndarray:
    """The route's weights ``(n_frames, n_targets)`` with the probed targets refined frame by frame.

    The renders are put onto the video's picture by one similarity for the whole take (fitted on
    MediaPipe's stable points over every frame); what differs per frame (the head's translation,
    scale, roll, pitch and yaw) is solved with the expression, so that no per-frame alignment on
    landmarks takes up part of the expression (a per-frame alignment on the stable points instead
    costs about a point on ICT: BENCHMARKS.md).
    """
    from scipy.optimize import lsq_linear

    from keyshape.alignment import procrustes
    from keyshape.schemes import stable_points

    stable = stable_points(478)
    probed = [names.index(n) for n in raised]
    seen = np.isfinite(video.points).all(axis=(1, 2)) & np.isfinite(base.points).all(axis=(1, 2))
    take = procrustes(base.points[seen][:, stable, :2].reshape(-1, 2),
                      video.points[seen][:, stable, :2].reshape(-1, 2))  # one similarity (Umeyama) for the take

    def align(points):
        return take.to_image(points[None])[0]

    frames = np.flatnonzero(seen)
    residuals = {f: video.points[f, :, :2] - align(base.points[f, :, :2]) for f in frames}
    if reference == "median":
        offset = np.median(np.stack(list(residuals.values())), axis=0)
    elif reference == "neutral":
        offset = residuals[neutral] if neutral in residuals else np.zeros((478, 2))
    else:
        offset = np.zeros((478, 2))
    out = route.copy()
    n = len(probed)
    for f in frames:
        at = align(base.points[f, :, :2])
        residual = (residuals[f] - offset).ravel()
        steps = np.maximum(np.minimum(route[f, probed] + delta, 1) - route[f, probed], 1e-3)
        columns = [(align(raised[name].points[f, :, :2]) - at).ravel() / step for name, step in zip(raised, steps)]
        depth = base.points[f, :, 2] - base.points[f, :, 2].mean()
        centred = at - at.mean(axis=0)
        one, zero = np.ones_like(depth), np.zeros_like(depth)
        columns += [np.column_stack(pair).ravel() for pair in (
            (zero, -depth), (depth, zero),  # pitch, yaw (from the render's own depths)
            (one, zero), (zero, one),  # move
            (centred[:, 0], centred[:, 1]), (-centred[:, 1], centred[:, 0]))]  # scale, roll
        design = np.vstack([np.column_stack(columns), np.diag([np.sqrt(ridge)] * n + [np.sqrt(turn)] * 6)])
        wanted = np.concatenate([residual, np.zeros(n + 6)])
        low = np.concatenate([-route[f, probed], [-1, -1], [-np.inf] * 4])
        high = np.concatenate([1 - route[f, probed] + 1e-12, [1, 1], [np.inf] * 4])
        if np.isfinite(design).all():
            out[f, probed] += lsq_linear(design, wanted, bounds=(low, high)).x[:n]
    return out


def through_keys(refined: np.ndarray, route: np.ndarray, key_weights: np.ndarray, probed, *,
                 ridge: float = 1e-3) -> np.ndarray:
    """The probed targets fitted on the key weights with a constant (what a ``map.json`` can carry)."""
    W = np.nan_to_num(key_weights)
    X = np.column_stack([np.ones(len(W)), W])
    penalty = ridge * len(W) * np.diag([0.0] + [1.0] * W.shape[1])
    out = route.copy()
    for j in probed:
        coef = np.linalg.solve(X.T @ X + penalty, X.T @ refined[:, j])
        out[:, j] = np.clip(X @ coef, 0, 1)
    return out


def probe(loop: Path, character: str, *, targets=PROBED, delta: float = 0.2, ridge: float = 1.0,
          turn: float = 1e-6, smooth: float = 3.0, rotation: str = "tracked", camera: str = "product",
          keep: Path | None = None, reference: str = "none") -> dict:
    """Scores (% per vertex set) of the route as written, refined per frame, and refined through the keys."""
    from scipy.ndimage import gaussian_filter1d

    from keyshape.io import load_rig, load_track, load_weights_csv
    from keyshape.io.gltf import read_glb_animation
    from keyshape.render import frame_points
    from keyshape.targets._propose import resolve_correspondence

    folder = loop / "ict" / "FaceXModel"
    rig = load_rig(folder, unit=0.01)
    landmarks = landmark_vertices(folder)
    colours = ict_colours(rig.vertices, landmarks)
    if character == "caricature":
        rig = caricature(rig, landmarks)
    run = loop / ("run" if character == "ICT" else "run_caricature")
    source = load_track(loop / "performance.npz")
    truth = truth_from_scores(source.blendshapes, source.blendshape_names, rig.names)
    written = read_glb_animation(run / "animation.glb")
    route = np.column_stack([written.weights[:, written.names.index(n)] for n in rig.names])
    video = load_track(run / "track.npz")
    key_weights = load_weights_csv(run / "weights.csv").values
    rotations = head_rotations((video if rotation == "tracked" else source).head_matrix)
    points = resolve_correspondence(run / "correspondence.json", rig, 478).points(rig.vertices[None])[0]
    if camera == "product":
        view, pivot = frame_points(points, margin=1.6), points.mean(axis=0)
    else:
        view, pivot = frame_points(rig.vertices[:FACE_AREA], margin=1.25), np.array([0.0, 0.0, -0.02])
    names = list(rig.names)
    with tempfile.TemporaryDirectory() as scratch:
        def track(weights, name):
            from keyshape.io import save_track

            kept = keep / f"{character}_{rotation}_{camera}_{Path(name).stem}.npz" if keep else None
            if kept is not None and kept.exists():
                return load_track(kept)
            tracked = render_and_track(rig, colours, weights, rotations, view, pivot, video.fps, Path(scratch) / name)
            if kept is not None:
                keep.mkdir(parents=True, exist_ok=True)
                save_track(tracked, kept)
            return tracked

        base = track(route, "base.mp4")
        raised = {}
        for name in targets:
            j = names.index(name)
            lifted = route.copy()
            lifted[:, j] = np.clip(lifted[:, j] + delta, 0, 1)
            raised[name] = track(lifted, f"{name}.mp4")
    import json

    neutral = int(json.loads((run / "take.json").read_text())["neutral_frame"])
    refined = refine(video, base, raised, route, names, delta=delta, ridge=ridge, turn=turn, reference=reference,
                     neutral=neutral)
    probed = [names.index(n) for n in targets]
    if smooth:
        refined[:, probed] = np.clip(gaussian_filter1d(refined[:, probed], smooth, axis=0), 0, 1)
    sets = vertex_sets(rig, landmarks)
    return {"route as written": vertex_error(rig, truth, route, sets),
            "refined, per frame": vertex_error(rig, truth, refined, sets),
            "refined, through the keys": vertex_error(rig, truth, through_keys(refined, route, key_weights, probed),
                                                      sets)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="the --out folder of bench_rendered_loop.py")
    parser.add_argument("--character", choices=("ICT", "caricature", "both"), default="both")
    parser.add_argument("--targets", default=",".join(PROBED), help="the targets refined (comma-separated)")
    parser.add_argument("--rotation", choices=("tracked", "truth"), default="tracked",
                        help="turn the renders by the video's tracked head rotation, or by the truth's")
    parser.add_argument("--camera", choices=("product", "video"), default="product",
                        help="frame on the corresponded points, or exactly as the benchmark framed its video")
    parser.add_argument("--smooth", type=float, default=3.0, help="Gaussian σ in frames of the refined weights")
    parser.add_argument("--ridge", type=float, default=1.0, help="λ, px² per unit weight²")
    parser.add_argument("--reference", choices=("none", "median", "neutral"), default="none",
                        help="subtract no offset from the residual, its take median, or its value at the neutral frame")
    parser.add_argument("--keep", type=Path, help="keep the renders' tracks here and reuse them on the next run")
    args = parser.parse_args(argv)
    characters = ("ICT", "caricature") if args.character == "both" else (args.character,)
    print("| character | route | face area | upper | lower |")
    print("|---|---|---|---|---|")
    for character in characters:
        start = time.perf_counter()
        scores = probe(args.out, character, targets=tuple(args.targets.split(",")), smooth=args.smooth,
                       ridge=args.ridge, rotation=args.rotation, camera=args.camera, keep=args.keep,
                       reference=args.reference)
        for route, s in scores.items():
            print(f"| {character} | {route} | {s['face']:.1f} % | {s['upper']:.1f} % | {s['lower']:.1f} % |")
        print(f"{character}: {time.perf_counter() - start:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
