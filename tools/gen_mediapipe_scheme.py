"""Regenerate ``src/keyshape/data/mediapipe478.json`` from MediaPipe's own tables.

Run from the project root: ``python tools/gen_mediapipe_scheme.py``. The runtime never
imports MediaPipe for the scheme; ``tests/test_schemes.py`` checks the JSON still matches.

Everything is derived from ``vision.FaceLandmarksConnections`` (contours and tessellation).
The one geometric choice — which face-oval points belong to the jaw — uses the neutral
frame of the embedded clip: oval points below the nose tip (landmark 1).

The left-right pairing (``mirror``: landmark i's mirror image is landmark ``mirror[i]``) comes
from MediaPipe's canonical face, which is exactly symmetric about x = 0: each of its 468 vertices
reflected lands on its partner. The ten iris points (not in the canonical face) are paired on
the embedded clip's first frame, reflected through the symmetry plane the 468 pairs define.
"""

import json
import sys
from pathlib import Path

import av
import mediapipe as mp
import numpy as np
from mediapipe.tasks.python import BaseOptions, vision

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "src" / "keyshape" / "data"
C = vision.FaceLandmarksConnections

# Named stable points for alignment (MediaPipe face-mesh ids): they barely move with expression.
STABLE = {
    "eye_corners": [33, 133, 362, 263],
    "nose_bridge": [168, 6, 197, 195],
    "forehead": [10, 151, 9],
    "temples": [127, 356, 162, 389],
}


def ids(connections):
    return sorted({i for c in connections for i in (c.start, c.end)})


def triangles(edges):
    nbr = {}
    for c in edges:
        nbr.setdefault(c.start, set()).add(c.end)
        nbr.setdefault(c.end, set()).add(c.start)
    tris = set()
    for a, na in nbr.items():
        for b in na:
            for c in na & nbr[b]:
                tris.add(tuple(sorted((a, b, c))))
    return sorted(tris)


def neutral_points():
    opts = vision.FaceLandmarkerOptions(
        base_options=BaseOptions(model_asset_path=str(DATA / "face_landmarker.task")),
        running_mode=vision.RunningMode.IMAGE,
    )
    with av.open(str(DATA / "WolfgangLanger_Pexels.mp4")) as c, \
            vision.FaceLandmarker.create_from_options(opts) as lm:
        frame = next(c.decode(video=0)).to_ndarray(format="rgb24")
        res = lm.detect(mp.Image(image_format=mp.ImageFormat.SRGB, data=frame))
    return np.array([[p.x, p.y, p.z] for p in res.face_landmarks[0]])


def mirror_pairs(pts):
    """(478,) int: the left-right partner of every landmark (see the module notes)."""
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial import cKDTree

    sys.path.insert(0, str(ROOT / "src"))
    from keyshape.capture.model_file import canonical_face

    canonical, _ = canonical_face()
    distance, pair = cKDTree(canonical).query(canonical * [-1.0, 1.0, 1.0])
    assert distance.max() < 1e-6 and (pair[pair] == np.arange(468)).all()
    pts = pts * [1.0, 1.0, 0.0]  # the irises' depth is MediaPipe's guess; pair them in the image plane
    moved = pts[:468] - pts[pair]
    normal = np.linalg.svd(moved, full_matrices=False)[2][0]
    offset = float(np.mean((pts[:468] + pts[pair]) @ normal) / 2)
    iris = np.arange(468, 478)
    reflected = pts[iris] - 2 * (pts[iris] @ normal - offset)[:, None] * normal
    cost = ((reflected[:, None] - pts[iris][None]) ** 2).sum(-1)
    cost[np.arange(10), np.arange(10)] = np.inf  # no iris point is its own mirror
    cost[:5, :5] = cost[5:, 5:] = np.inf  # the partner lies in the other iris
    rows, cols = linear_sum_assignment(cost)
    out = np.concatenate([pair, iris[cols[np.argsort(rows)]]])
    assert (out[out] == np.arange(478)).all()
    return [int(i) for i in out]


def main():
    pts = neutral_points()
    oval = ids(C.FACE_LANDMARKS_FACE_OVAL)
    jaw = [i for i in oval if pts[i, 1] > pts[1, 1]]
    brows = ids(C.FACE_LANDMARKS_LEFT_EYEBROW) + ids(C.FACE_LANDMARKS_RIGHT_EYEBROW)
    left_eye = ids(C.FACE_LANDMARKS_LEFT_EYE)  # irises carry gaze: not blended
    right_eye = ids(C.FACE_LANDMARKS_RIGHT_EYE)
    mouth = sorted(set(ids(C.FACE_LANDMARKS_LIPS)) | set(jaw))
    scheme = {
        "name": "mediapipe478",
        "n_landmarks": 478,
        "contours": {
            "lips": ids(C.FACE_LANDMARKS_LIPS),
            "left_eye": ids(C.FACE_LANDMARKS_LEFT_EYE),
            "right_eye": ids(C.FACE_LANDMARKS_RIGHT_EYE),
            "left_eyebrow": ids(C.FACE_LANDMARKS_LEFT_EYEBROW),
            "right_eyebrow": ids(C.FACE_LANDMARKS_RIGHT_EYEBROW),
            "left_iris": ids(C.FACE_LANDMARKS_LEFT_IRIS),
            "right_iris": ids(C.FACE_LANDMARKS_RIGHT_IRIS),
            "nose": ids(C.FACE_LANDMARKS_NOSE),
            "face_oval": oval,
            "jaw": jaw,
        },
        "contour_edges": {
            name: [[c.start, c.end] for c in getattr(C, "FACE_LANDMARKS_" + name.upper())]
            for name in ("lips", "left_eye", "right_eye", "left_eyebrow", "right_eyebrow",
                         "left_iris", "right_iris", "face_oval", "nose")
        },
        "region_schemes": {
            "whole": {"whole": sorted(set(brows + left_eye + right_eye + mouth))},
            "upper-lower": {"upper": sorted(set(brows + left_eye + right_eye)), "lower": mouth},
            "eyes": {"brows": sorted(brows), "left_eye": sorted(left_eye),
                     "right_eye": sorted(right_eye), "mouth": mouth},
        },
        "stable": STABLE,
        "triangles": triangles(C.FACE_LANDMARKS_TESSELATION),
        "mirror": mirror_pairs(pts),
    }
    (DATA / "mediapipe478.json").write_text(json.dumps(scheme, separators=(",", ":")) + "\n")
    print(f"wrote {DATA / 'mediapipe478.json'}: {len(scheme['triangles'])} triangles, jaw {len(jaw)} points")


if __name__ == "__main__":
    main()
