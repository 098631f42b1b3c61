"""The closed loop on ICT-FaceKit: known ARKit weights in, the same face out through proposed targets.

1. Animate the ICT-FaceKit rig (57 ARKit-style shapes, 26,719 vertices) with known weights: a
   sequence of expressions (smile, jaw open, pucker, brows up, ...) with blinks, 600 frames at 30 fps.
2. Take its 68 landmark vertices (iBUG order, from ``vertex_indices.json``) as the "performance":
   turned by a small head motion and projected orthographically to pixels (x, y and, for a 3D
   track, z on the x scale), with 0.3 px noise.
3. Run keyshape on it: key shapes (8 per region) and weights (``discover_keys``, ``solve_take``).
4. Propose the targets on the same face, both routes, with the known landmark vertices as the
   correspondence:

   * **mapping**: each key as a non-negative mix of ICT's own 57 shapes (``propose_mapping``);
   * **transfer**: ICT's neutral only, one new target per key (``propose_targets``);

5. Compare the animated vertices with the truth: the mean vertex error as a percentage of the mean
   displacement from neutral (100 % = leaving the face neutral), over the face area (vertices
   0-9408 per ``vertex_indices.json``) and over the whole mesh (head, mouth socket, teeth, eyes).

    python benchmarks/bench_closed_loop.py                      # ../shared/data/ict-facekit
    python benchmarks/bench_closed_loop.py --ict PATH.tar.xz --keys 8 12

The test ``tests/test_closed_loop.py`` runs the same code with the figures as bounds.
"""

from __future__ import annotations

import argparse
import json
import tarfile
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from keyshape.app import discover_keys, solve_take
from keyshape.containers import Rig, Track, blend
from keyshape.io.rig import load_rig
from keyshape.targets import Correspondence, propose_mapping, propose_targets, retarget

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "ict-facekit"
ARCHIVE = "ICT-FaceKit_FaceXModel_neutral_and_expressions.tar.xz"
FACE_AREA = 9409  # vertices 0..9408 are the face area (vertex_indices.json)

# Expressions as ARKit-style gains; "_L"/"_R" shapes are driven together.
PRESETS = (
    {"mouthSmile": 1.0, "cheekSquint": 0.4},
    {"jawOpen": 0.7, "mouthLowerDown": 0.3},
    {"mouthPucker": 1.0},
    {"mouthFunnel": 0.8, "jawOpen": 0.2},
    {"mouthFrown": 1.0, "browDown": 0.4},
    {"mouthPress": 0.8},
    {"mouthStretch": 0.8},
    {"browInnerUp": 1.0, "browOuterUp": 0.8, "eyeWide": 0.4},
    {"browDown": 1.0, "eyeSquint": 0.5},
    {"noseSneer": 0.8, "mouthUpperUp": 0.5},
    {"jawLeft": 0.6},
    {"mouthRight": 0.6},
    {"mouthRollLower": 0.7, "mouthRollUpper": 0.5},
)


def extract_ict(archive: Path, into: Path) -> Path:
    """The ``FaceXModel`` folder of the archive, extracted once under ``into``."""
    done = into / f".extracted-{archive.stat().st_size}"
    if not done.exists():
        with tarfile.open(archive) as tar:
            tar.extractall(into, filter="data")
        done.touch()
    return into / "FaceXModel"


def landmark_vertices(folder: Path) -> np.ndarray:
    """(68,) int: ICT's landmark vertices in iBUG order, from the extracted ``vertex_indices.json``."""
    ids = json.loads((folder / "vertex_indices.json").read_text())["idx_to_landmark_verts"]
    return np.array(json.loads(ids) if isinstance(ids, str) else ids, dtype=np.int64)


def arkit_performance(names, *, n_frames: int = 600, seed: int = 0) -> np.ndarray:
    """Known weights ``(n_frames, n_targets)`` in [0, 1]: expressions one after another, and blinks."""
    rng = np.random.default_rng(seed)
    time_axis = np.arange(n_frames)
    weights = np.zeros((n_frames, len(names)))

    def channels(base):
        return [i for i, n in enumerate(names) if n in (base, base + "_L", base + "_R")]

    start = 30
    while start < n_frames - 20:
        preset = PRESETS[rng.integers(len(PRESETS))]
        length, amplitude = int(rng.integers(15, 45)), rng.uniform(0.5, 1.0)
        envelope = amplitude * np.sin(np.pi * np.clip((time_axis - start) / length, 0, 1)) ** 2
        for base, gain in preset.items():
            weights[:, channels(base)] += gain * envelope[:, None]
        start += int(length * rng.uniform(0.6, 1.1))
    for blink in rng.choice(np.arange(40, n_frames - 10), 12, replace=False):
        weights[:, channels("eyeBlink")] += np.exp(-0.5 * ((time_axis - blink) / 2.5) ** 2)[:, None]
    return np.clip(weights, 0, 1)


def landmark_track(points: np.ndarray, *, dims: int, head_motion: bool, seed: int = 0,
                   pixels_per_metre: float = 2500.0, noise: float = 0.3) -> Track:
    """The landmarks ``(n_frames, 68, 3)`` (metres, glTF axes) seen by an orthographic camera, as pixels."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed + 1)
    t = np.arange(len(points))
    angles = np.radians(np.stack([6 * np.sin(t / 40), 4 * np.sin(t / 27), 3 * np.sin(t / 33)], axis=1))
    rotations = Rotation.from_euler("YXZ", angles * float(head_motion)).as_matrix()
    centred = points - points[0].mean(axis=0)
    turned = np.einsum("fij,fpj->fpi", rotations, centred) * pixels_per_metre
    # glTF (x right, y up, z toward the camera) -> image (x right, y down, z away)
    image = np.stack([320 + turned[..., 0], 240 - turned[..., 1], -turned[..., 2]], axis=-1)[..., :dims]
    return Track(image + rng.normal(scale=noise, size=image.shape), 30.0)


@dataclass(frozen=True)
class LoopResult:
    """Mean vertex error, % of the mean displacement from neutral, per route and vertex set."""

    dims: int
    n_keys: int
    head_motion: bool
    figures: dict  # route -> {"face": %, "all": %}
    seconds: dict  # route -> s


def closed_loop(rig: Rig, landmarks: np.ndarray, *, dims: int = 3, n_keys: int = 8, head_motion: bool = True,
                n_frames: int = 600, seed: int = 0) -> LoopResult:
    """Run the loop (module docstring) and measure both routes against the truth."""
    weights = arkit_performance(rig.names, n_frames=n_frames, seed=seed)
    seen = blend(rig.vertices[landmarks], rig.deltas[:, landmarks], weights)
    track = landmark_track(seen, dims=dims, head_motion=head_motion, seed=seed)
    keys = discover_keys(track, regions="upper-lower", n_keys=n_keys, neutral=0)
    solved = solve_take(track, keys)
    key_weights = np.nan_to_num(solved.weights.values)
    correspondence = Correspondence.from_vertex_ids(landmarks, n_landmarks=len(landmarks))
    figures = {"neutral": _error(rig, weights,
                                 lambda frames: np.broadcast_to(rig.vertices, (len(frames), *rig.vertices.shape)))}
    seconds = {}
    start = time.perf_counter()
    mapping = propose_mapping(keys, rig, correspondence=correspondence)
    seconds["mapping"] = time.perf_counter() - start
    target_weights = retarget(solved.weights, mapping).values
    figures["mapping"] = _error(rig, weights, lambda frames: rig.pose(target_weights[frames]))
    start = time.perf_counter()
    proposed = propose_targets(keys, rig, correspondence=correspondence)
    seconds["transfer"] = time.perf_counter() - start
    figures["transfer"] = _error(rig, weights, lambda frames: proposed.pose(key_weights[frames]))
    return LoopResult(dims, n_keys, head_motion, figures, seconds)


def _error(rig: Rig, weights: np.ndarray, estimate, *, chunk: int = 40) -> dict:
    """Mean vertex error over mean displacement, %, over the face area and the whole mesh.

    Frames are posed ``chunk`` at a time (a whole take of ICT-FaceKit would take gigabytes).
    """
    sums = np.zeros(4)  # error face, error all, displacement face, displacement all
    for start in range(0, len(weights), chunk):
        frames = np.arange(start, min(start + chunk, len(weights)))
        truth = rig.pose(weights[frames])
        error = np.linalg.norm(estimate(frames) - truth, axis=2)
        moved = np.linalg.norm(truth - rig.vertices, axis=2)
        sums += [error[:, :FACE_AREA].sum(), error.sum(), moved[:, :FACE_AREA].sum(), moved.sum()]
    return {"face": 100 * sums[0] / sums[2], "all": 100 * sums[1] / sums[3]}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ict", type=Path, default=SHARED / ARCHIVE, help="the ICT-FaceKit archive")
    parser.add_argument("--keys", type=int, nargs="+", default=[8], help="key shapes per region")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as scratch:
        folder = extract_ict(args.ict, Path(scratch))
        rig = load_rig(folder, unit=0.01)
        landmarks = landmark_vertices(folder)
    print("| track | head motion | keys/region | route | face area | whole mesh | propose (s) |")
    print("|---|---|---|---|---|---|---|")
    for n_keys in args.keys:
        for dims, head in ((3, True), (2, False)):
            result = closed_loop(rig, landmarks, dims=dims, n_keys=n_keys, head_motion=head)
            for route in ("neutral", "mapping", "transfer"):
                fig = result.figures[route]
                took = f"{result.seconds[route]:.1f}" if route in result.seconds else ""
                print(f"| {dims}D | {'yes' if head else 'no'} | {n_keys} | {route} | {fig['face']:.1f} % | "
                      f"{fig['all']:.1f} % | {took} |")


if __name__ == "__main__":
    main()
