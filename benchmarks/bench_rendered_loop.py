"""The rendered closed loop: a real performance, rendered, tracked, and put back on the rig.

1. **Truth.** ICT-FaceKit (57 ARKit-style shapes) is driven by a real person's timing and
   co-activation: MediaPipe's 52 ARKit scores of the embedded clip (``WolfgangLanger_Pexels.mp4``,
   472 frames), lightly smoothed, with the clip's head rotation (MediaPipe's head matrix).
2. **Video.** Each frame is rendered by keyshape's own renderer (OpenGL on EGL), coloured so the
   tracker sees a face (skin, lips, brows, lashes, irises, teeth; ICT's translucent eye overlays
   left out), its eyeballs turned by the gaze weights as an actor's eyes turn (ICT's ``eyeLook*``
   targets move only the lids), and written to an H.264 MP4.
3. **The route under test.** ``keyshape run VIDEO --rig ict.glb --auto-targets`` (through
   :func:`keyshape.app.run_take`), ``ict.glb`` being ICT as a user's file holds it: its colours
   (COLOR_0), no translucent overlays. The real MediaPipe tracks the video, key shapes are found,
   weights solved, and the key → ICT-shape mapping proposed on the rig's own render, as it looks.
4. **Scores**, as mean vertex error over the mean displacement from neutral (100 % = a frozen
   face), on ICT's face area and on its upper (brows, eyes) and lower (nose tip down) halves:

   * ``keyshape``: the target weights of the run's ``animation.glb`` (its weights through its
     ``map.json``, the gaze targets following the gaze scores frame by frame);
   * ``mediapipe``: MediaPipe's own 52 scores of the rendered video driving the same rig (the peer's
     naive path);
   * ``mediapipe less rest``: the same less MediaPipe's reading of the character at rest (its still
     render, :func:`rest_reading`), clipped at 0; ``mediapipe less neutral``: less the scores of the
     key set's neutral frame instead (the peer's path with a calibration);
   * ``oracle (>= 0)``: the best non-negative key → shape mapping, fitted on the truth from the same
     solved key weights (what a perfect proposal could reach);
   * ``oracle (signed + constant)``: the same with signed gains and a constant term.

5. **The transfer route** (``--transfer``): the same head with its shapes dropped, so
   ``--auto-targets`` carries each key's landmark motion onto the mesh (expression transfer, with
   and without the per-feature proportion rescaling); the character posed by the solved key
   weights through those targets, scored the same way.
6. **A second head.** The same video drives a caricature of ICT (:func:`caricature`: eyes 30 %
   larger, mouth 25 % wider, nose 20 % smaller, chin shorter; every target warped with it), so the
   character's proportions differ from the performer's; the truth is the same weights on it.

7. **Another rig family** (``--family rpm``, :func:`rpm_loop`): a Ready Player Me avatar
   (``../shared/data/rpm/``: a skinned, textured full body; another mesh, other sculpted shapes,
   textures instead of vertex colours), rendered with its texture colours and scored on its head.

    python benchmarks/bench_rendered_loop.py                          # ../shared/data/ict-facekit
    python benchmarks/bench_rendered_loop.py --out /tmp/loop          # keep the video and the runs
    python benchmarks/bench_rendered_loop.py --family rpm             # ../shared/data/rpm/RPM_Template_Mesh_XR.glb

The whole loop takes about two minutes on two cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import itertools

from bench_closed_loop import ARCHIVE, FACE_AREA, SHARED, extract_ict, landmark_vertices

# ICT-FaceKit "light" vertex ranges (inclusive), from the ICT-FaceKit documentation, checked
# against the mesh (each range is where its part sits)
PARTS = {
    "face": (0, 9408), "head": (9409, 11247), "mouth_socket": (11248, 13293), "eye_sockets": (13294, 14061),
    "gums": (14062, 17038), "teeth": (17039, 21450), "eyeball_left": (21451, 23020),
    "eyeball_right": (23021, 24590), "overlays": (24591, 25350), "eyelashes": (25351, 26718),
}
SKIN, LIPS, BROWS, LASHES = (0.80, 0.62, 0.52), (0.62, 0.30, 0.30), (0.25, 0.17, 0.12), (0.10, 0.08, 0.07)
SCLERA, IRIS, PUPIL, TEETH, INSIDE = (0.92, 0.90, 0.86), (0.30, 0.20, 0.12), (0.03, 0.03, 0.03), \
    (0.90, 0.88, 0.80), (0.35, 0.12, 0.12)


def _part(name: str) -> np.ndarray:
    lo, hi = PARTS[name]
    return np.arange(lo, hi + 1)


def ict_colours(vertices: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """Base colours ``(n_vertices, 3)``: skin, lips and brows (from the 68 landmarks), lashes, eyes, mouth."""
    from matplotlib.path import Path as Polygon

    colours = np.tile(SKIN, (len(vertices), 1))
    face = _part("face")
    xy = vertices[face, :2]
    lm = vertices[landmarks]
    lips = Polygon(lm[48:60, :2]).contains_points(xy, radius=0.0015)
    colours[face[lips]] = LIPS
    for brow in (lm[17:22, :2], lm[22:27, :2]):
        near = np.min(np.linalg.norm(xy[:, None] - _densify(brow)[None], axis=2), axis=1) < 0.0045
        colours[face[near & (vertices[face, 2] > lm[27, 2] - 0.03)]] = BROWS
    for part in ("mouth_socket", "gums"):
        colours[_part(part)] = INSIDE
    colours[_part("teeth")] = TEETH
    colours[_part("eyelashes")] = LASHES
    for side in ("eyeball_left", "eyeball_right"):
        ids = _part(side)
        centre = vertices[ids].mean(axis=0) - np.array([0.0, 0.0, 0.004])
        direction = vertices[ids] - centre
        cos = direction[:, 2] / np.linalg.norm(direction, axis=1)
        colours[ids] = SCLERA
        colours[ids[cos > 0.86]] = IRIS
        colours[ids[cos > 0.97]] = PUPIL
    return colours


def _densify(polyline: np.ndarray, n: int = 8) -> np.ndarray:
    t = np.linspace(0, 1, n, endpoint=False)
    pieces = [a + (b - a) * t[:, None] for a, b in itertools.pairwise(polyline)]
    return np.vstack([*pieces, polyline[-1:]])


def rendered_faces(faces: np.ndarray) -> np.ndarray:
    """The triangles to draw: ICT's translucent eye overlays (lacrimal fluid, blend, occlusion) left out."""
    lo, hi = PARTS["overlays"]
    return faces[~((faces >= lo) & (faces <= hi)).any(axis=1)]


def truth_from_scores(scores: np.ndarray, score_names, rig_names, *, sigma: float = 1.0) -> np.ndarray:
    """ICT weights ``(n_frames, n_targets)`` from MediaPipe's ARKit scores ``(n_frames, 52)``, smoothed."""
    from scipy.ndimage import gaussian_filter1d

    table = arkit_to_rig(score_names, rig_names)
    weights = np.nan_to_num(scores) @ table.T
    return np.clip(gaussian_filter1d(weights, sigma, axis=0, mode="nearest"), 0, 1) if sigma else weights


def arkit_to_rig(score_names, rig_names) -> np.ndarray:
    """(n_targets, n_scores) 0/1: MediaPipe's ``xxxLeft`` drives ``xxx_L``; an unsided score drives both sides."""
    table = np.zeros((len(rig_names), len(score_names)))
    index = {n: i for i, n in enumerate(rig_names)}
    for j, name in enumerate(score_names):
        for side, suffix in (("Left", "_L"), ("Right", "_R")):
            if name.endswith(side) and name[: -len(side)] + suffix in index:
                table[index[name[: -len(side)] + suffix], j] = 1
                break
        else:
            for target in (name, name + "_L", name + "_R"):
                if target in index:
                    table[index[target], j] = 1
    return table


def head_rotations(head_matrix: np.ndarray) -> np.ndarray:
    """Rotations ``(n_frames, 3, 3)`` (glTF axes) of MediaPipe's head matrices, relative to their median pose."""
    from scipy.spatial.transform import Rotation

    linear = np.asarray(head_matrix, dtype=float)[:, :3, :3]
    u, _, vt = np.linalg.svd(linear)
    rotations = Rotation.from_matrix(u @ vt)
    rest = Rotation.from_rotvec(np.median(rotations.as_rotvec(), axis=0))
    return (rotations * rest.inv()).as_matrix()


@dataclass(frozen=True, eq=False)
class Stage:
    """How a head is shown in the loop's video.

    ``faces (n_faces, 3)``: the triangles drawn; ``framed (n,)``: the vertex ids the camera frames;
    ``pivot (3,)``: what the head turns about; ``colours (n_vertices, 3)``; ``eyes``: ``(ids, centre)``
    per eyeball turned by the gaze weights (ICT, whose ``eyeLook*`` targets move only the lids).
    """

    faces: np.ndarray
    framed: np.ndarray
    pivot: np.ndarray
    colours: np.ndarray
    eyes: tuple = ()


def ict_stage(rig, colours: np.ndarray, *, turn_eyes: bool = True) -> Stage:
    """ICT as the loop shows it: no translucent overlays, the face framed, the eyeballs turned."""
    eyes = tuple((_part(side), _sphere_centre(rig.vertices[_part(side)])) for side in ("eyeball_left", "eyeball_right"))
    return Stage(rendered_faces(rig.faces), _part("face"), np.array([0.0, 0.0, -0.02]), colours,
                 eyes if turn_eyes else ())


def render_video(rig, weights: np.ndarray, rotations: np.ndarray, path: Path, fps: float, stage,
                 *, size: int = 512, turn_eyes: bool = True) -> Path:
    """The rig posed frame by frame, turned by ``rotations`` about the stage's pivot, as an MP4 ``size`` pixels square.

    ``stage``: a :class:`Stage`, or ICT's colours ``(n_vertices, 3)`` (:func:`ict_stage`, ``turn_eyes``).

    With the stage's ``eyes`` the eyeballs turn with the frame's gaze weights (:func:`eye_rotations`),
    as an actor's do: ICT's ``eyeLook*`` targets move only the lids, so without it the irises stay
    centred whatever the gaze, and the tracker reads the lids' shift as a look the other way.
    """
    from keyshape.render import frame_points, make_renderer
    from keyshape.render.encode import VideoWriter

    if not isinstance(stage, Stage):
        stage = ict_stage(rig, stage, turn_eyes=turn_eyes)
    pivot = np.asarray(stage.pivot)
    camera = frame_points(rig.vertices[stage.framed], margin=1.25)
    turns = eye_rotations(weights, rig.names) if stage.eyes else None
    with make_renderer(stage.faces, size, size, n_vertices=rig.n_vertices, backend="gl",
                       colours=stage.colours) as renderer, VideoWriter(path, size, size, fps, crf=16) as out:
        for f in range(len(weights)):
            posed = rig.pose(weights[f : f + 1])[0]
            if turns is not None:
                for (ids, centre), turn in zip(stage.eyes, turns[f]):
                    posed[ids] = (posed[ids] - centre) @ turn.T + centre
            out.write(renderer.render((posed - pivot) @ rotations[f].T + pivot, camera))
    return path


def rest_reading(rig, stage: Stage, path: Path, *, n_frames: int = 15) -> dict:
    """MediaPipe's scores ``{ARKit name: median score}`` of the character at rest, rendered as the loop
    renders it (``n_frames`` still frames): how the tracker reads this face doing nothing."""
    from keyshape.capture import track_video

    still = np.zeros((n_frames, rig.n_targets))
    render_video(rig, still, np.tile(np.eye(3), (n_frames, 1, 1)), path, 30.0, stage)
    tracked = track_video(path, progress=False)
    median = np.nanmedian(tracked.blendshapes, axis=0)
    return {str(n): float(v) for n, v in zip(tracked.blendshape_names, median)}


def eye_rotations(weights: np.ndarray, names, *, degrees: float = 30.0) -> np.ndarray:
    """Eyeball rotations ``(n_frames, 2, 3, 3)`` (left eye at +x, then right) from ARKit gaze weights.

    Each ``eyeLook*`` weight is a turn of ``degrees`` (keyshape's ``GAZE_DEGREES``): the left eye
    turns toward +x by ``Out_L − In_L``, the right toward −x by ``Out_R − In_R``, both up by
    ``Up − Down``. ICT faces +z with +y up.
    """
    from scipy.spatial.transform import Rotation

    index = {n: i for i, n in enumerate(names)}

    def w(name):
        return weights[:, index[name]] if name in index else np.zeros(len(weights))

    out = np.empty((len(weights), 2, 3, 3))
    for e, (side, sign) in enumerate((("L", 1.0), ("R", -1.0))):
        yaw = np.radians(degrees) * sign * (w(f"eyeLookOut_{side}") - w(f"eyeLookIn_{side}"))
        pitch = np.radians(degrees) * (w(f"eyeLookUp_{side}") - w(f"eyeLookDown_{side}"))
        # yaw about +y takes +z toward +x; looking up takes +z toward +y, a negative turn about +x
        out[:, e] = (Rotation.from_rotvec(np.column_stack([np.zeros_like(yaw), yaw, np.zeros_like(yaw)]))
                     * Rotation.from_rotvec(np.column_stack([-pitch, np.zeros_like(pitch), np.zeros_like(pitch)]))
                     ).as_matrix()
    return out


def _sphere_centre(points: np.ndarray) -> np.ndarray:
    """The least-squares sphere centre of ``points (n, 3)``: ``|p|² = 2 c·p + k``."""
    design = np.column_stack([2 * points, np.ones(len(points))])
    solution = np.linalg.lstsq(design, (points**2).sum(axis=1), rcond=None)[0]
    return solution[:3]


def vertex_error(rig, truth: np.ndarray, estimate: np.ndarray, vertex_sets: dict) -> dict:
    """Mean vertex error / mean displacement from neutral, %, per vertex set (rig weights in, both)."""
    return posed_error(rig, rig, np.clip(estimate, 0, 1), truth, vertex_sets)


def oracles(key_weights: np.ndarray, truth: np.ndarray) -> dict:
    """The best key → target mappings fitted on the truth: non-negative, and signed with a constant."""
    from scipy.optimize import nnls

    W = np.nan_to_num(key_weights)
    nonneg = np.stack([nnls(W, truth[:, j])[0] for j in range(truth.shape[1])])
    design = np.hstack([W, np.ones((len(W), 1))])
    signed = np.linalg.lstsq(design, truth, rcond=None)[0]
    return {"oracle (>= 0)": W @ nonneg.T, "oracle (signed + constant)": design @ signed}


def caricature(rig, landmarks: np.ndarray):
    """ICT with other proportions: a smooth warp of the neutral, every target warped with it.

    ``φ(p) = p + Σ_f g_f(p) (S_f − 1)(p − c_f)``: each feature ``f`` (the eyes, the mouth, the nose,
    the chin) scaled by ``S_f`` about its centre ``c_f`` with a Gaussian falloff ``g_f``; a target
    becomes ``φ(N + D) − φ(N)``.
    """
    from keyshape.containers import Rig

    lm = rig.vertices[landmarks]
    features = [(lm[36:42].mean(axis=0), (1.3, 1.3, 1.3), 0.012), (lm[42:48].mean(axis=0), (1.3, 1.3, 1.3), 0.012),
                (lm[48:68].mean(axis=0), (1.25, 1.05, 1.0), 0.02), (lm[30], (0.8, 0.8, 0.8), 0.012),
                (lm[8], (1.0, 0.8, 1.0), 0.03)]

    def warp(points):
        out = points.copy()
        for centre, scale, sigma in features:
            offset = points - centre
            falloff = np.exp(-(offset**2).sum(axis=-1) / (2 * sigma**2))[..., None]
            out += falloff * offset * (np.asarray(scale) - 1)
        return out

    neutral = warp(rig.vertices)
    deltas = np.stack([warp(rig.vertices + d) - neutral for d in rig.deltas])
    return Rig(neutral, rig.faces, deltas, rig.names)


@dataclass(frozen=True)
class Loop:
    """Scores (% per vertex set) per route, and what the run found."""

    scores: dict
    detection_rate: float
    n_keys: int
    seconds: float
    steps: dict = field(default_factory=dict)  # map.json's refined "steps": the step each judged target keeps


def rendered_loop(rig_folder: Path, out: Path, *, performance: Path | None = None,
                  second_head: bool = False, transfer: bool = False, floor: bool = False) -> dict[str, Loop]:
    """Run the loop of the module docstring on ICT, writing the video and the runs under ``out``
    (``floor``: ``run --floor``).

    Returns ``{"ICT": Loop}`` and, with ``second_head``, ``"caricature"`` too.
    """
    from keyshape.io import load_rig, load_track

    start = time.perf_counter()
    rig = load_rig(rig_folder, unit=0.01)
    landmarks = landmark_vertices(rig_folder)
    source = load_track(performance) if performance else _demo_track(out)
    truth = truth_from_scores(source.blendshapes, source.blendshape_names, rig.names)
    rotations = head_rotations(source.head_matrix)
    colours = ict_colours(rig.vertices, landmarks)
    stage = ict_stage(rig, colours)
    video = render_video(rig, truth, rotations, out / "ict.mp4", source.fps, stage)
    character = as_it_looks(rig, colours, out / "ict.glb")
    rest = rest_reading(rig, stage, out / "ict_rest.mp4")
    loops = {"ICT": _run_and_score(video, character, rig, vertex_sets(rig, landmarks), truth, out / "run", start,
                                   rest, transfer, floor=floor)}
    if second_head:
        start = time.perf_counter()
        other = caricature(rig, landmarks)
        character = as_it_looks(other, colours, out / "caricature.glb")
        rest = rest_reading(other, ict_stage(other, colours), out / "caricature_rest.mp4")
        loops["caricature"] = _run_and_score(video, character, other, vertex_sets(other, landmarks), truth,
                                             out / "run_caricature", start, rest, transfer,
                                             track=load_track(out / "run" / "track.npz"), floor=floor)
    return loops


RPM = SHARED.parent / "rpm"
RPM_HEAD = "Wolf3D_Head"


def rpm_loop(glb: Path, out: Path, *, performance: Path | None = None, floor: bool = False) -> dict[str, Loop]:
    """The loop on a Ready Player Me avatar (``glb``: a skinned, textured full body, 52 ARKit targets).

    The meshes with morph targets (head, eyes, teeth; in their bind pose, as the file stores
    them) are rendered with their texture colours (sampled per vertex: :func:`keyshape.io.gltf.read_colours`),
    the face framed, the head turned about its centre; the avatar's eyes turn by its own ``eyeLook*``
    targets. ``run`` is handed the user's file itself. Scored on the head mesh's vertices that its
    targets move (:func:`rpm_vertex_sets`). Returns ``{glb.stem: Loop}``.
    """
    from keyshape.io import load_rig, load_track
    from keyshape.io.gltf import read_colours

    start = time.perf_counter()
    rig = load_rig(glb)
    sets = rpm_vertex_sets(rig, head_vertices(glb))
    source = load_track(performance) if performance else _demo_track(out)
    truth = truth_from_scores(source.blendshapes, source.blendshape_names, rig.names)
    rotations = head_rotations(source.head_matrix)
    rgba = read_colours(glb)
    faces = np.asarray(rig.faces)[rgba[rig.faces, 3].mean(axis=1) >= 0.5]
    head = head_vertices(glb)
    stage = Stage(faces, sets["face"], rig.vertices[head].mean(axis=0), rgba[:, :3])
    video = render_video(rig, truth, rotations, out / f"{glb.stem}.mp4", source.fps, stage)
    rest = rest_reading(rig, stage, out / f"{glb.stem}_rest.mp4")
    return {glb.stem: _run_and_score(video, glb, rig, sets, truth, out / f"run_{glb.stem}", start, rest,
                                     floor=floor)}


def head_vertices(glb: Path) -> np.ndarray:
    """The ids ``(n,)`` of the ``Wolf3D_Head`` mesh's vertices in :func:`keyshape.io.load_rig`'s rig of ``glb``."""
    import pygltflib

    from keyshape.io.gltf import read_meshes

    document = pygltflib.GLTF2().load(str(glb))
    _, parts = read_meshes(glb)
    heads = [p for p in parts if document.meshes[p.mesh].name == RPM_HEAD]
    if not heads:
        raise SystemExit(f"{glb}: no {RPM_HEAD} mesh among those with morph targets")
    return np.concatenate([np.arange(p.start, p.start + p.count) for p in heads])


def rpm_vertex_sets(rig, head: np.ndarray, *, moved: float = 5e-4) -> dict:
    """The face (the head vertices some target but ``tongueOut`` moves more than ``moved`` metres) and
    its halves above and below the nose tip (the face's most forward vertex near the midline)."""
    reach = np.linalg.norm(np.delete(rig.deltas, [i for i, n in enumerate(rig.names) if n == "tongueOut"], axis=0),
                           axis=2).max(axis=0)
    face = head[reach[head] > moved]
    points = rig.vertices[face]
    middle = face[np.abs(points[:, 0] - np.median(points[:, 0])) < 0.01]
    nose_tip = rig.vertices[middle[np.argmax(rig.vertices[middle, 2])], 1]
    upper = face[rig.vertices[face, 1] > nose_tip]
    return {"face": face, "upper": upper, "lower": np.setdiff1d(face, upper)}


def as_it_looks(rig, colours: np.ndarray, path: Path) -> Path:
    """The rig as a user's file would hold it: a .glb with its colours (COLOR_0) and without the
    translucent eye overlays, so ``--auto-targets`` renders the character as it looks."""
    from keyshape.containers import Rig, Weights
    from keyshape.io.gltf import write_glb

    shown = Rig(rig.vertices, rendered_faces(rig.faces), rig.deltas, rig.names)
    return write_glb(path, shown, Weights(np.zeros((0, rig.n_targets)), rig.names, 30.0), colours=colours)


def _run_and_score(video: Path, rig_file: Path, rig, sets: dict, truth: np.ndarray, run: Path, start: float,
                   rest: dict, transfer: bool = False, track=None, floor: bool = False) -> Loop:
    """``keyshape run VIDEO --rig RIG --auto-targets``, its result and the other routes scored on ``rig``
    (the same run with ``--no-refine`` too, on its track); ``rest``: MediaPipe's reading of the
    character at rest (:func:`rest_reading`), ``sets``: the vertex sets scored; ``track``: the video's
    track when it was made already (the same video on a second head)."""
    from keyshape.app import RunOptions, run_take
    from keyshape.io import load_keys, load_track, load_weights_csv
    from keyshape.io.gltf import read_glb_animation

    summary = run_take(video, run, RunOptions(rig=rig_file, auto_targets=True, floor=floor, preview=False,
                                              extras=False), progress=False, track=track)
    tracked = load_track(run / "track.npz")
    key_weights = load_weights_csv(run / "weights.csv")
    written = read_glb_animation(run / "animation.glb")  # the keyshape animation, as a viewer plays it
    table = arkit_to_rig(tracked.blendshape_names, rig.names)
    scores = np.nan_to_num(tracked.blendshapes)
    at_rest = np.array([rest.get(str(n), 0.0) for n in tracked.blendshape_names])
    neutral = scores[load_keys(run / "keys.json").neutral_frame]
    estimates = {"keyshape": np.column_stack([written.weights[:, written.names.index(n)] for n in rig.names]),
                 "mediapipe": scores @ table.T,
                 "mediapipe less rest": np.clip(scores - at_rest, 0, 1) @ table.T,
                 "mediapipe less neutral": np.clip(scores - neutral, 0, 1) @ table.T}
    # the same take without render and compare: the targets follow MediaPipe's scores alone
    run_take(video, run.with_name(run.name + "_no_refine"), RunOptions(rig=rig_file, auto_targets=True, refine=False,
                                                                        floor=floor, preview=False, extras=False),
             progress=False, track=tracked)
    plain = read_glb_animation(run.with_name(run.name + "_no_refine") / "animation.glb")
    estimates["keyshape, --no-refine"] = np.column_stack([plain.weights[:, plain.names.index(n)] for n in rig.names])
    estimates.update(oracles(key_weights.values, truth))
    scores = {route: vertex_error(rig, truth, np.nan_to_num(e), sets) for route, e in estimates.items()}
    if transfer:
        scores.update(transfer_routes(rig, run, key_weights.values, truth, sets))
    steps = (json.loads((run / "map.json").read_text()).get("refined") or {}).get("steps", {})
    return Loop(scores, summary.detection_rate, summary.keys.n_keys, time.perf_counter() - start, steps)


def transfer_routes(rig, run: Path, key_weights: np.ndarray, truth: np.ndarray, sets: dict) -> dict:
    """The transfer route's scores: ``rig`` without its shapes, one target per key of the ``run``
    proposed by expression transfer (on the run's correspondence), posed by the run's key weights;
    with and without the per-feature proportion rescaling."""
    from keyshape.containers import Rig
    from keyshape.io import load_keys
    from keyshape.targets import propose_targets
    from keyshape.targets._propose import resolve_correspondence

    keys = load_keys(run / "keys.json")
    plain = Rig(rig.vertices, rendered_faces(rig.faces), np.zeros((0, rig.n_vertices, 3)), ())
    corr = resolve_correspondence(run / "correspondence.json", plain, keys.n_landmarks)
    out = {}
    for route, rescale in (("transfer (shapes dropped)", True), ("transfer, no proportion rescaling", False)):
        proposed = propose_targets(keys, plain, correspondence=corr, rescale=rescale)
        out[route] = posed_error(rig, proposed, np.nan_to_num(key_weights), truth, sets)
    return out


def posed_error(rig, proposed, weights: np.ndarray, truth: np.ndarray, sets: dict, *, chunk: int = 40) -> dict:
    """:func:`vertex_error` of another rig on the same mesh (``proposed`` posed by ``weights``)."""
    sums = {name: np.zeros(2) for name in sets}
    for start in range(0, len(truth), chunk):
        frames = slice(start, start + chunk)
        posed_truth, posed = rig.pose(truth[frames]), proposed.pose(weights[frames])
        error = np.linalg.norm(posed - posed_truth, axis=2)
        moved = np.linalg.norm(posed_truth - rig.vertices, axis=2)
        for name, ids in sets.items():
            sums[name] += [error[:, ids].sum(), moved[:, ids].sum()]
    return {name: 100 * s[0] / s[1] for name, s in sums.items()}


def vertex_sets(rig, landmarks: np.ndarray) -> dict:
    """Face area, and its upper (above the nose tip) and lower halves."""
    face = np.arange(FACE_AREA)
    nose_tip = rig.vertices[landmarks[30], 1]
    upper = face[rig.vertices[face, 1] > nose_tip]
    return {"face": face, "upper": upper, "lower": np.setdiff1d(face, upper)}


def _demo_track(out: Path):
    """MediaPipe's scores and head matrix of the embedded clip (tracked once, kept in ``out``)."""
    from keyshape.capture import track_to_file
    from keyshape.cli.demo import demo_clip
    from keyshape.io import load_track

    path = out / "performance.npz"
    if not path.exists():
        track_to_file(demo_clip(), path, progress=False)
    return load_track(path)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--family", choices=("ict", "rpm"), default="ict",
                        help="the rig family: ICT-FaceKit and its caricature, or a Ready Player Me avatar")
    parser.add_argument("--ict", type=Path, default=SHARED / ARCHIVE, help="the ICT-FaceKit archive")
    parser.add_argument("--rpm", type=Path, default=RPM / "RPM_Template_Mesh_XR.glb",
                        help="the Ready Player Me avatar (--family rpm)")
    parser.add_argument("--performance", type=Path, default=None,
                        help="a track .npz with MediaPipe scores and head matrix (default: the embedded clip)")
    parser.add_argument("--out", type=Path, default=None, help="folder for the video and the run (default: temporary)")
    parser.add_argument("--json", type=Path, default=None, help="also write the scores here")
    parser.add_argument("--no-second-head", action="store_true", help="only ICT itself as the character")
    parser.add_argument("--floor", action="store_true", help="the runs with run --floor (issue 35)")
    parser.add_argument("--transfer", action="store_true",
                        help="also score the transfer route (each head with its shapes dropped; ICT only)")
    args = parser.parse_args(argv)
    if args.family == "rpm" and args.transfer:
        parser.error("--transfer runs on ICT only")
    with tempfile.TemporaryDirectory() as scratch:
        out = args.out or Path(scratch)
        out.mkdir(parents=True, exist_ok=True)
        if args.family == "rpm":
            loops = rpm_loop(args.rpm, out, performance=args.performance, floor=args.floor)
        else:
            folder = extract_ict(args.ict, out / "ict")
            loops = rendered_loop(folder, out, performance=args.performance, second_head=not args.no_second_head,
                                  transfer=args.transfer, floor=args.floor)
    print("| character | route | face area | upper | lower |")
    print("|---|---|---|---|---|")
    for character, loop in loops.items():
        for route, s in loop.scores.items():
            print(f"| {character} | {route} | {s['face']:.1f} % | {s['upper']:.1f} % | {s['lower']:.1f} % |")
    for character, loop in loops.items():
        print(f"{character}: face found in {100 * loop.detection_rate:.1f} % of the frames; {loop.n_keys} keys; "
              f"{loop.seconds:.0f} s; steps kept {loop.steps}")
    if args.json:
        args.json.write_text(json.dumps({c: loop.scores for c, loop in loops.items()}, indent=1))


if __name__ == "__main__":
    main()
