"""Build ``src/keyshape/data/hand_landmarker.task`` from MediaPipe's own hand models.

MediaPipe's Tasks API loads a hand landmarker from a ``.task`` bundle: a zip holding
``hand_detector.tflite`` (the palm detector) and ``hand_landmarks_detector.tflite`` (21 hand
landmarks and a presence score). The mediapipe wheels up to 0.10.14 carry both models (Apache-2.0)
for their legacy ``solutions.hands`` API, as ``mediapipe/modules/palm_detection/palm_detection_full.tflite``
and ``mediapipe/modules/hand_landmark/hand_landmark_full.tflite``; later wheels carry neither.
This script downloads that wheel with pip (no dependencies, nothing installed), takes the two
files out unmodified and stores them under the bundle's names.

    python tools/make_hand_model.py          # writes src/keyshape/data/hand_landmarker.task

The bundle's sha256 is checked by ``keyshape.capture.mediapipe.HAND_MODEL_SHA256``.
"""

from __future__ import annotations

import hashlib
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

WHEEL = "mediapipe==0.10.14"
MEMBERS = {"hand_detector.tflite": "mediapipe/modules/palm_detection/palm_detection_full.tflite",
           "hand_landmarks_detector.tflite": "mediapipe/modules/hand_landmark/hand_landmark_full.tflite"}
OUT = Path(__file__).resolve().parents[1] / "src" / "keyshape" / "data" / "hand_landmarker.task"


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
                        "--python-version", "3.11", "--platform", "manylinux2014_x86_64", "-d", tmp, WHEEL],
                       check=True, stdout=subprocess.DEVNULL)
        wheel = next(Path(tmp).glob("mediapipe-*.whl"))
        with zipfile.ZipFile(wheel) as source, zipfile.ZipFile(OUT, "w", zipfile.ZIP_STORED) as bundle:
            for name, member in MEMBERS.items():
                info = zipfile.ZipInfo(name, date_time=(2024, 5, 8, 0, 0, 0))  # fixed: the same bytes every time
                bundle.writestr(info, source.read(member))
    print(f"{OUT}: sha256 {hashlib.sha256(OUT.read_bytes()).hexdigest()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
