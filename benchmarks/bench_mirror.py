"""Key shapes that carry over to a new take: mirrored keys and ``--extend``, on real capture.

Keys are found on the **first half** of a take; the **second half** is the new take. Scores:

* **landmark error**: the RMS landmark error (% of the inter-ocular distance) of the second half's
  best bounded blend (``0 <= w <= 1``) of the keys, per region (``keyshape.app.fit_errors``), on the
  embedded clip (a real person) and on the rendered ICT-FaceKit loop (``bench_rendered_loop.py``:
  ICT driven by the clip's own timing, rendered, tracked by the real MediaPipe);
* **vertex error** (ICT only): the character driven by the second half's solved key weights with
  the *true* ICT mesh of each key frame as its target (what a perfect artist would sculpt: the
  true mesh at the key frame minus the true mesh at the neutral frame; a mirrored key's target
  is its source's mirrored on ICT's symmetric topology), against the true mesh of every frame:
  mean vertex error over mean displacement from the rig's rest pose (100 % = a frozen face,
  the measure of ``bench_rendered_loop.py``).

Rows: no mirrors; mirrors with the default ``min_reach`` (and the other thresholds with
``--sweep``); ``keys --extend`` of the first-half keys with the second half.

    python benchmarks/bench_mirror.py                         # tracks the clip, renders the ICT loop
    python benchmarks/bench_mirror.py --demo-track T.npz --ict-track R.npz --performance P.npz --sweep

``--ict-track`` is the rendered loop's track (``bench_rendered_loop.py --out DIR --keep`` leaves
``DIR/run/track.npz``) and ``--performance`` the track whose MediaPipe scores drove it.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_closed_loop import ARCHIVE, SHARED, extract_ict, landmark_vertices


def halves(track):
    """The take's two halves (scores, visibility and all), and where the second starts."""
    cut = track.n_frames // 2
    return track[:cut], track[cut:], cut


def key_sets(first, second, *, reaches=(None,)):
    """name -> KeyShapes: without mirrors, with mirrors at each ``min_reach``, extended."""
    from dataclasses import replace

    from keyshape.alignment import choose_neutral
    from keyshape.app import discover_keys, extend_keys
    from keyshape.keyshapes import MIN_REACH
    from keyshape.schemes import stable_points

    plain = discover_keys(first, mirror=False)
    out = {"no mirrors": plain}
    for given in reaches:
        reach = MIN_REACH if given is None else given
        label = f"mirrors (min_reach {reach:g})" + (" [default]" if reach == MIN_REACH else "")
        out[label] = discover_keys(first, mirror=True, min_reach=reach)
    default = next(v for k, v in out.items() if "[default]" in k)
    out["mirrors + --extend"] = extend_keys(default, second, take="second")
    # the neutral by the median-shape rule instead of the default least-activated frame
    median = choose_neutral(first, stable=stable_points(first.n_landmarks))
    out[f"mirrors, median-shape neutral (frame {median})"] = discover_keys(first, mirror=True, neutral=int(median))
    out["mirrors, no visibility (hidden frames may be keys)"] = discover_keys(replace(first, visibility=None),
                                                                              mirror=True)
    return out


def landmark_errors(keys, second) -> dict:
    from keyshape.app import fit_errors

    return fit_errors(second, keys)[0]


def ict_pairs(vertices: np.ndarray) -> np.ndarray:
    """Each ICT vertex's mirror partner across x = 0 (ICT's topology is symmetric)."""
    from scipy.spatial import cKDTree

    _, pairs = cKDTree(vertices).query(vertices * [-1.0, 1.0, 1.0])
    return pairs


def ict_vertex_error(keys, second, cut, rig, truth, pairs, sets) -> dict:
    """The second half driven by keys whose targets are the true meshes of their frames."""
    from keyshape.app import solve_take

    # weight 0 is the actor's neutral frame: the character's base is the true mesh there, and a
    # key's target its true mesh minus that base
    base = np.tensordot(truth[keys.neutral_frame], rig.deltas, axes=1)
    # each key is sculpted on its own region: the upper keys above the nose tip, the lower ones below
    upper_half = rig.vertices[:, 1] >= rig.vertices[sets["upper"], 1].min()
    masks = {"upper": upper_half, "lower": ~upper_half}
    targets = []
    for k in range(keys.n_keys):
        frame = int(keys.frames[k]) + (cut if keys.takes[k] == "second" else 0)
        delta = np.tensordot(truth[frame], rig.deltas, axes=1) - base
        if keys.mirror_of[k]:
            delta = delta[pairs] * [-1.0, 1.0, 1.0]
        targets.append(delta * masks.get(keys.key_regions[k], np.ones(len(delta), dtype=bool))[:, None])
    targets = np.array(targets)
    weights = np.nan_to_num(solve_take(second, keys).weights.values)
    truth2 = truth[cut:cut + second.n_frames]
    sums = {name: np.zeros(2) for name in sets}
    for start in range(0, len(truth2), 40):
        f = slice(start, start + 40)
        posed_truth = rig.pose(truth2[f])
        posed = rig.vertices + base + np.tensordot(weights[f], targets, axes=1)
        error = np.linalg.norm(posed - posed_truth, axis=2)
        moved = np.linalg.norm(posed_truth - rig.vertices, axis=2)
        for name, ids in sets.items():
            sums[name] += [error[:, ids].sum(), moved[:, ids].sum()]
    return {name: 100 * s[0] / s[1] for name, s in sums.items()}


def _counts(keys) -> str:
    return f"{keys.n_keys} ({int(keys.mirrored.sum())} mirrored)"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demo-track", type=Path, default=None, help="the embedded clip's track (default: track it)")
    parser.add_argument("--ict-track", type=Path, default=None,
                        help="the rendered ICT loop's track (default: render and track it)")
    parser.add_argument("--performance", type=Path, default=None,
                        help="the track whose scores drove the ICT loop (default: the demo track)")
    parser.add_argument("--ict", type=Path, default=SHARED / ARCHIVE, help="the ICT-FaceKit archive")
    parser.add_argument("--sweep", action="store_true", help="also the other min_reach thresholds")
    args = parser.parse_args(argv)

    from keyshape.capture import track_to_file
    from keyshape.cli.demo import demo_clip
    from keyshape.io import load_rig, load_track

    reaches = (0.0, 0.1, 0.2, 0.25, 0.3, None, 0.5, 0.7) if args.sweep else (None,)
    with tempfile.TemporaryDirectory() as temporary:
        scratch = Path(temporary)
        demo_path = args.demo_track or track_to_file(demo_clip(), scratch / "demo.npz", progress=False)
        demo = load_track(demo_path)
        print(f"## embedded clip: keys from frames 0..{demo.n_frames // 2 - 1}, second half solved")
        print("| keys | count | upper | lower |\n|---|---|---|---|")
        first, second, _ = halves(demo)
        for label, keys in key_sets(first, second, reaches=reaches).items():
            e = landmark_errors(keys, second)
            print(f"| {label} | {_counts(keys)} | {e['upper']:.2f} | {e['lower']:.2f} |")

        if not args.ict.exists():
            print(f"\n(no ICT archive at {args.ict}: the ICT rows need ../shared)")
            return
        from bench_rendered_loop import (
            head_rotations,
            ict_colours,
            render_video,
            truth_from_scores,
            vertex_sets,
        )

        folder = extract_ict(args.ict, scratch / "ict")
        rig = load_rig(folder, unit=0.01)
        landmarks = landmark_vertices(folder)
        performance = load_track(args.performance) if args.performance else demo
        truth = truth_from_scores(performance.blendshapes, performance.blendshape_names, rig.names)
        if args.ict_track is None:
            video = render_video(rig, truth, head_rotations(performance.head_matrix), scratch / "ict.mp4",
                                 performance.fps, ict_colours(rig.vertices, landmarks))
            ict_path = track_to_file(video, scratch / "ict.npz", progress=False)
        else:
            ict_path = args.ict_track
        tracked = load_track(ict_path)
        first, second, cut = halves(tracked)
        pairs, sets = ict_pairs(rig.vertices), vertex_sets(rig, landmarks)
        print("\n## rendered ICT loop: keys from the first half, true key meshes as targets, second half solved")
        print("| keys | count | landmarks upper | landmarks lower | vertices face | vertices upper | vertices lower |")
        print("|---|---|---|---|---|---|---|")
        for label, keys in key_sets(first, second, reaches=reaches).items():
            e = landmark_errors(keys, second)
            v = ict_vertex_error(keys, second, cut, rig, truth, pairs, sets)
            print(f"| {label} | {_counts(keys)} | {e['upper']:.2f} | {e['lower']:.2f} | {v['face']:.1f} % "
                  f"| {v['upper']:.1f} % | {v['lower']:.1f} % |")


if __name__ == "__main__":
    main()
