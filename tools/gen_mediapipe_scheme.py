"""Regenerate ``src/keyshape/data/mediapipe478.json`` from MediaPipe's own tables.

Run from the project root: ``python tools/gen_mediapipe_scheme.py``. The runtime never
imports MediaPipe for the scheme; ``tests/test_schemes.py`` checks the JSON still matches.

Everything is derived from ``vision.FaceLandmarksConnections`` (contours and tessellation).
The one geometric choice — which face-oval points belong to the jaw — uses the neutral
frame of the embedded clip: oval points below the nose tip (landmark 1).
"""

import json
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
    }
    (DATA / "mediapipe478.json").write_text(json.dumps(scheme, separators=(",", ":")) + "\n")
    print(f"wrote {DATA / 'mediapipe478.json'}: {len(scheme['triangles'])} triangles, jaw {len(jaw)} points")


if __name__ == "__main__":
    main()
