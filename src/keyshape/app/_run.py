"""One take, start to finish: what ``keyshape run``, ``demo`` and ``batch`` do.

``run_take`` tracks a video, discovers (or reuses) the key shapes, solves the weights, drives a
character and writes every output into one folder. Outputs are staged in a hidden folder beside
and moved in only when everything succeeded, in one step, so a failure or a signal leaves no
half-written or mixed take behind. A reused folder keeps no stale output: the files an earlier run
wrote (its ``take.json`` records them, :func:`keyshape.io.take.written_by`) that this run did not
write again (its ``preview.mp4`` under ``--no-preview``, its ``map.json``, ...) are removed; any
other file is left alone, whatever its name. The rig, mapping and key set are read before the
tracking starts.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..containers import KeyShapes, Rig, Track
from ..defaults import (
    DEFAULT_METHOD,
    DEFAULT_MIRROR,
    DEFAULT_N_KEYS,
    DEFAULT_REGIONS,
    DEFAULT_SMOOTHNESS,
    DEFAULT_UPPER,
    MAX_ERROR,
)
from ..exceptions import InputError
from ..io.atomic import staged_folder

__all__ = ["RunOptions", "TakeSummary", "run_take", "OUTPUT_FILES", "default_character_extras"]

OUTPUT_FILES = ("track.npz", "keys.json", "weights.csv", "animation.glb", "take.json")
ANIMATION_SUFFIXES = {"fbx": ".fbx", "blend": ".blend", "usd": ".usda"}  # RunOptions.formats


@dataclass(frozen=True)
class RunOptions:
    """Settings of a run (the command line's options)."""

    rig: Path | None = None
    mapping: Path | None = None
    keys: Path | None = None  # reuse this key set instead of discovering one
    regions: str | Path = DEFAULT_REGIONS
    n_keys: int | str = DEFAULT_N_KEYS  # or "auto"
    max_error: float = MAX_ERROR  # % inter-ocular distance, for n_keys="auto"
    method: str = DEFAULT_METHOD
    mirror: bool = DEFAULT_MIRROR  # add mirrored keys where they add reach
    neutral: int | None = None
    capture: dict = field(default_factory=dict)  # start, end, fps, face, one_euro
    smoothness: float = DEFAULT_SMOOTHNESS
    upper: float | None = DEFAULT_UPPER
    convex: bool = False
    auto_targets: bool = False  # propose the rig's targets (or a mapping) for the keys
    correspondence: Path | None = None  # auto_targets: landmark -> mesh file (default: found)
    front: str = "auto"  # auto_targets: the axis the character's face looks along (default: looked for)
    meshes: tuple | None = None  # auto_targets, glTF rig: the meshes to read (default: morph meshes, else the head's)
    normalize: bool = False  # auto_targets, mapping route: each target driven fully by its best key
    refine: bool = True  # auto_targets, score mapping: refine the targets the scores barely see (render and compare)
    floor: bool = False  # auto_targets, score mapping: start from the scores less the rest reading (issue 35)
    preview: bool = True
    extras: bool = True
    formats: tuple[str, ...] = ()  # the animation also as animation.<suffix>: "fbx", "blend", "usd"


@dataclass(frozen=True)
class TakeSummary:
    """What a run found, for people (printed) and for batch tables."""

    take: str
    n_frames: int
    detection_rate: float
    keys_per_region: dict[str, int]
    error_pct: float  # RMS reconstruction error, % of the inter-ocular distance (NaN if unknown)
    gaps: str
    files: tuple[str, ...]
    seconds: float
    keys: KeyShapes = field(repr=False, compare=False, default=None)


def _rig_and_mapping(options: RunOptions, keys: KeyShapes, scores=None, loaded: Rig | None = None
                     ) -> tuple[Rig, object, bool, object, bool]:
    """The character, the key -> target mapping, whether the rig file is kept whole, the
    :class:`~keyshape.targets._propose.AutoTargets` proposal (None without ``auto_targets``), and
    whether targets the file lacks were made (mirrored keys'); ``loaded``: ``options.rig`` read
    already (by :func:`_read_inputs`)."""
    from ..io.rig import load_rig
    from ..targets import Mapping

    if options.rig is None:
        from ..targets import default_character, with_gaze_targets

        rig = with_gaze_targets(default_character(keys))  # a stylised head with proposed targets (issue 7)
        return rig, Mapping.by_name(keys.names, rig.names, allow_extra=True), False, None, False
    if options.auto_targets:
        from ..targets import auto_targets

        auto = auto_targets(keys, options.rig, correspondence=options.correspondence, front=options.front,
                            normalize=options.normalize, scores=scores, meshes=options.meshes)
        # transfer onto a glTF file: the new targets go into a copy of it, kept whole (textures, body)
        onto_file = auto.route == "transfer" and Path(options.rig).suffix.lower() in (".glb", ".gltf")
        return auto.rig, auto.mapping, auto.route == "mapping" or onto_file, auto, onto_file
    read = loaded if loaded is not None else load_rig(options.rig)
    if options.mapping is not None:
        return read, Mapping.from_file(options.mapping, targets=read.names), True, None, False
    rig = with_mirrored_targets(read, keys)  # the same object when nothing was made
    from ..targets import GAZE_NAMES

    gaze_only = set(rig.names) - set(keys.names) <= set(GAZE_NAMES)  # e.g. a take's own animation.glb
    return rig, Mapping.by_name(keys.names, rig.names, allow_extra=gaze_only), True, None, rig is not read


def _refined(auto, options: RunOptions, track: Track, weights, progress: bool):
    """The score mapping with the targets the scores barely see refined on the landmarks
    (:func:`keyshape.targets.refine_mapping`: render and compare); None when the rig has none of them."""
    import warnings
    from dataclasses import replace

    from ..targets import key_targets, refinable_targets, refine_mapping, with_floor

    if not refinable_targets(auto.rig.names):  # not an ARKit rig: nothing to refine, nothing to say
        return None
    from ._stages import stage

    stage("render and compare: refining the targets the scores barely see")
    colours = None
    if options.rig is not None and Path(options.rig).suffix.lower() in (".glb", ".gltf"):
        from ..io.gltf import read_colours

        colours = read_colours(options.rig)  # rendered as it looks, as for the correspondence
    floor = _floor(auto, options, track)
    mapping = auto.mapping
    if floor:  # rendered as it will be driven: the floor but on the targets judged and the key targets
        mapping = with_floor(mapping, floor, {*key_targets(auto.rig.names), *refinable_targets(auto.rig.names)})
    refinement = refine_mapping(mapping, auto.rig, auto.correspondence, track, weights, colours=colours,
                                progress=progress, floor=floor or None)
    if refinement.reason:
        warnings.warn(f"render and compare skipped: {refinement.reason}; the targets follow the scores",
                      stacklevel=2)
        if floor:
            refinement = replace(refinement, mapping=with_floor(auto.mapping, floor, key_targets(auto.rig.names)))
    return refinement


def _floor(auto, options: RunOptions, track: Track) -> tuple:
    """The floor's score channels (:func:`keyshape.targets.score_floor`), or () (``--no-floor``, no scores)."""
    from ..targets import score_floor

    if not options.floor or track.blendshapes is None or not track.blendshape_names:
        return ()
    exclude = ()
    if options.rig is not None and Path(options.rig).suffix.lower() in (".glb", ".gltf"):
        from ..io.gltf import eye_nodes
        from ..targets import GAZE_TARGETS

        if eye_nodes(options.rig) is not None:
            exclude = GAZE_TARGETS  # its eyes turn by their nodes, with the irises' gaze: not twice
    return score_floor(auto.rig.names, track.blendshape_names, rest=auto.correspondence.rest_scores,
                       exclude=exclude)


def _refined_note(refinement) -> dict | None:
    """What render and compare did, for ``map.json`` (and the report)."""
    if refinement is None:
        return None
    if not refinement.targets:
        return {"targets": [], "skipped": refinement.reason}
    before, after = refinement.residual_px
    note = {"targets": list(refinement.targets), "residual_px": [round(before, 3), round(after, 3)]}
    if refinement.steps:
        note["steps"] = dict(refinement.steps)
    return note


def with_mirrored_targets(rig: Rig, keys: KeyShapes) -> Rig:
    """A sculpted character with its mirrored keys' targets made where the artist left them out or
    neutral (:func:`keyshape.targets.complete_mirrors`); the rig as it is otherwise."""
    from ..targets import complete_mirrors

    mirror_of = {n: m for n, m in zip(keys.names, keys.mirror_of) if m}
    return complete_mirrors(rig, mirror_of)[0] if mirror_of else rig


def _read_inputs(options: RunOptions, video: Path, track: Track | None) -> tuple[Rig | None, KeyShapes | None]:
    """Read (and so check) the rig, the mapping and the key set before the tracking starts, so a
    broken one fails in a second, not after minutes of work; check ``neutral`` against the frame
    range to track. Returns (the rig or None, the key set or None)."""
    from ..io.keys_json import load_keys

    rig = _read_rig(options) if options.rig is not None else None
    if options.mapping is not None and rig is not None and not options.auto_targets:
        from ..targets import Mapping

        Mapping.from_file(options.mapping, targets=rig.names)
    keys = load_keys(options.keys) if options.keys is not None else None
    if rig is not None and options.mapping is None and not options.auto_targets:
        _check_drivable(rig, options, keys)
    if isinstance(options.neutral, int) and track is None and keys is None:
        _check_neutral_in_range(options, video)
    return rig, keys


def _read_rig(options: RunOptions) -> Rig:
    """The rig, read (and so checked) before the tracking; with ``auto_targets`` a glTF file without
    morph targets is a neutral to transfer onto (its head's mesh: :func:`keyshape.io.gltf.read_meshes`)."""
    path = Path(options.rig)
    if options.auto_targets and path.suffix.lower() in (".glb", ".gltf"):
        from ..io.gltf import check_gltf_file, read_meshes

        check_gltf_file(path)
        return read_meshes(path, meshes=options.meshes)[0]
    from ..io.rig import load_rig

    return load_rig(path)


def _check_drivable(rig: Rig, options: RunOptions, keys: KeyShapes | None) -> None:
    from ..schemes import resolve_regions
    from ._drivable import check_drivable

    regions = list(keys.regions) if keys is not None else list(resolve_regions(options.regions, 478))
    check_drivable(rig, options.rig, regions=regions, keys=keys)


def _check_neutral_in_range(options: RunOptions, video: Path) -> None:
    from ..capture import probe
    from ..exceptions import UsageError

    capture = options.capture
    declared = probe(video, fps=capture.get("fps")).n_frames
    end = capture.get("end")
    last = (min(end, declared) if end is not None and declared else end or declared) - capture.get("start", 0)
    if last and options.neutral >= last:
        raise UsageError(f"--neutral must be a frame in 0..{last - 1} (frames of the take, counted from "
                         f"--start); got {options.neutral}")


def _error_pct(solved, keys: KeyShapes) -> float:
    from ..schemes import eye_corners

    corners = eye_corners(keys.n_landmarks)
    if corners is None:
        return float("nan")
    iod = np.linalg.norm(keys.neutral[corners[0], :2] - keys.neutral[corners[1], :2])
    idx = np.unique(np.concatenate(list(keys.regions.values())))
    recon = keys.pose(solved.weights.values)[:, idx]
    valid = solved.aligned.valid
    diff = recon[valid] - solved.aligned.points[valid][:, idx]
    return float(100 * np.sqrt(np.mean(np.sum(diff**2, axis=2))) / iod)


def _write_outputs(stage: Path, video: Path, track, keys, solved, rig, mapping, options,
                   keep_file: bool = True, remade: bool = False) -> None:
    from ..io import export
    from ..io.keys_json import save_keys
    from ..io.take import save_take_info
    from ..io.track import save_track
    from ..io.weights_csv import save_weights_csv
    from ..targets import drive_gaze, retarget

    save_track(track, stage / "track.npz")
    save_keys(keys, stage / "keys.json")
    save_weights_csv(solved.weights, stage / "weights.csv")
    anim = retarget(solved.weights, mapping)
    anim = drive_gaze(anim, mapping, track.blendshapes, track.blendshape_names)  # map.json's "gaze"
    source = options.rig if keep_file and options.rig is not None and options.rig.is_file() and \
        options.rig.suffix.lower() in (".glb", ".gltf") else None  # kept whole, animation added
    if source is not None and remade:  # targets made (mirrored keys', or transferred): the file gets them
        from ..io.gltf import write_gltf_targets

        source = write_gltf_targets(source, stage / ".character.glb", rig, meshes=options.meshes)
    eyes = solved.gaze.rotations() if solved.gaze is not None else None
    colours = None
    if options.rig is None:  # the stylised head: its colours, and its eyes turned by the gaze targets
        anim, colours = default_character_extras(anim, solved.gaze)
    elif options.mapping is None and not options.auto_targets:  # a rig's own ARKit gaze targets: the irises
        anim = drive_gaze_targets(anim, solved.gaze, taken=keys.names)
    export(anim, stage / "animation.glb", rig=rig, poses=solved.poses, source=source, eyes=eyes, colours=colours)
    for chosen in options.formats:  # Blender's FBX / .blend (io.blender), USD
        export(anim, stage / f"animation{ANIMATION_SUFFIXES[chosen]}", rig=rig, poses=solved.poses,
               source=source, eyes=eyes)
    if keep_file and options.rig is not None and options.rig.suffix.lower() == ".vrm":  # the avatar's own targets
        export(anim, stage / "animation.vrma", poses=solved.poses, source=options.rig, eyes=eyes)
    save_take_info(stage / "take.json", video=video, track=track, keys=keys,
                   neutral=_neutral_file(options, keys))
    (stage / ".character.glb").unlink(missing_ok=True)


def _neutral_file(options, keys: KeyShapes) -> Path | None:
    """The still image or clip the keys' neutral comes from (``--neutral FILE``), if it does."""
    neutral = options.neutral
    return neutral if isinstance(neutral, Path) and keys.neutral_take == neutral.name else None


def drive_gaze_targets(anim, gaze, taken=()):
    """``anim`` with its ARKit gaze targets (``eyeLookInLeft`` ...) but those named in ``taken``
    (driven by keys) turned by the irises' gaze, at the built-in head's 30° per unit weight
    (:func:`keyshape.targets.gaze_weights`); frame numbers and times kept."""
    import dataclasses

    from ..targets import GAZE_NAMES, gaze_weights

    free = [n for n in GAZE_NAMES if n in anim.names and n not in taken]
    if gaze is None or not free:
        return anim
    values = np.array(anim.values, dtype=float)
    driven = gaze_weights(gaze.yaw, gaze.pitch)
    for name in free:
        values[:, anim.names.index(name)] = driven[:, GAZE_NAMES.index(name)]
    return dataclasses.replace(anim, values=values)


def default_character_extras(anim, gaze):
    """The built-in head's animation with its gaze targets driven by ``gaze`` (if any), and its colours."""
    from ..targets import stylised_head

    return drive_gaze_targets(anim, gaze), stylised_head().colours


def _check_formats(formats) -> None:
    unknown = [f for f in formats if f not in ANIMATION_SUFFIXES]
    if unknown:
        raise InputError(f"formats must be among {sorted(ANIMATION_SUFFIXES)}; got {unknown}")
    if {"fbx", "blend"} & set(formats):
        from ..io.blender import check_blender

        check_blender()  # before the tracking, not after it


def run_take(video: str | Path, outdir: str | Path, options: RunOptions = RunOptions(), *,
             progress: bool = True, track: Track | None = None) -> TakeSummary:
    """Track ``video``, find key shapes, solve, drive the character, write everything to ``outdir``.

    ``track``: the take's track when it was made already (``video`` is then only recorded).

    Writes ``track.npz``, ``keys.json``, ``weights.csv``, ``animation.glb`` (and
    ``animation.fbx`` / ``.blend`` / ``.usda`` for ``options.formats``; ``animation.vrma``, VRM
    Animation 1.0, for a ``.vrm`` rig driven through its own expressions), ``take.json`` and,
    with ``options.extras``, ``preview.mp4`` (``options.preview``), the pictures and ``report.html``.
    Everything is staged and moved into ``outdir`` at the end; on error nothing is moved.
    """
    from ..io.atomic import claimed_folder

    with claimed_folder(outdir):  # a second run into the same folder meanwhile is refused before its work
        return _run_take(video, outdir, options, progress=progress, track=track)


def _run_take(video: str | Path, outdir: str | Path, options: RunOptions, *, progress: bool,
              track: Track | None) -> TakeSummary:
    """:func:`run_take`, once its output folder is claimed."""
    from ..capture import track_video
    from ._pipeline import discover_keys, key_scores, solve_take
    from ._stages import stage as announce

    start = time.perf_counter()
    video, outdir = Path(video), Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise InputError(f"{outdir}: exists and is not a folder")
    _check_formats(options.formats)
    loaded_rig, keys = _read_inputs(options, video, track)
    if track is None:
        announce(f"tracking {video.name}")
        track = track_video(video, progress=progress, **options.capture)
    if keys is None:
        announce(f"finding the key shapes of {track.n_frames} frames")
        keys = discover_keys(track, regions=options.regions, n_keys=options.n_keys,
                             method=options.method, neutral=options.neutral, take=video.name,
                             upper=options.upper, max_error=options.max_error, mirror=options.mirror)
    announce(f"solving the weights of {keys.n_keys} keys")
    solved = solve_take(track, keys, smoothness=options.smoothness, upper=options.upper,
                        convex=options.convex)
    scores = key_scores(keys, track, solved.weights,
                        same_take=options.keys is None and not isinstance(options.neutral, Path))  # reused keys too
    announce("driving the character" + (" (proposing its targets)" if options.auto_targets else ""))
    rig, mapping, keep_file, auto, remade = _rig_and_mapping(options, keys, scores, loaded_rig)
    refinement = None
    if auto is not None and auto.route == "mapping" and options.refine and auto.correspondence is not None:
        refinement = _refined(auto, options, track, solved.weights, progress)
        mapping = refinement.mapping if refinement is not None else mapping
    elif auto is not None and auto.route == "mapping" and _floor(auto, options, track):
        from ..targets import key_targets, with_floor

        mapping = with_floor(mapping, _floor(auto, options, track), key_targets(auto.rig.names))
    from ..io.take import record_written, written_by

    earlier = written_by(outdir)  # what an earlier run wrote here: the stale ones go, nothing else
    with staged_folder(outdir, owned=earlier.__contains__, record="take.json") as stage:
        announce("writing the animation and the take's files")
        _write_outputs(stage, video, track, keys, solved, rig, mapping, options, keep_file, remade)
        if auto is not None:  # the proposal, to check, edit and reuse (--map / --correspondence)
            if auto.correspondence is not None:  # None for a VRM avatar (its scores alone)
                auto.correspondence.save(stage / "correspondence.json")
            if auto.route == "mapping":
                mapping.save(stage / "map.json", refined=_refined_note(refinement))
        if options.extras:
            from ..report import write_take_extras

            announce("rendering the preview video, the pictures and the report" if options.preview
                     else "drawing the pictures and the report")
            write_take_extras(stage, progress=progress, preview=options.preview)
        files = tuple(sorted(p.name for p in stage.iterdir()))
        record_written(stage / "take.json", files)
    return TakeSummary(video.name, track.n_frames, float(track.valid.mean()),
                       {r: len(keys.keys_of(r)) for r in keys.regions}, _error_pct(solved, keys),
                       str(solved.gaps), files, time.perf_counter() - start, keys)
