"""The side-by-side preview video: the actor with tracked landmarks | the retargeted character.

One output frame per track frame, at the track's frame rate::

    ┌──────────────────────────────┬───────────────────┐
    │ source frame + landmarks     │ character, same    │
    │ (one colour per region)      │ head rotation      │
    ├──────────────────────────────┴───────────────────┤
    │ ▇ ▂ ▅ ...  current key weights, labelled          │
    └──────────────────────────────────────────────────┘
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..containers import KeyShapes, Rig, Track, Weights
from ..exceptions import InputError
from ..io.atomic import atomic_path
from ..schemes import mediapipe_scheme
from ._backend import make_renderer
from .camera import frame_points
from .draw import (
    HIDDEN_COLOUR,
    OTHER_COLOUR,
    WeightStrip,
    caption,
    draw_crosses,
    draw_landmarks,
    landmark_colours,
    region_palette,
    resize_to_height,
)
from .encode import VideoWriter

__all__ = ["render_preview", "rotations_from_quaternions", "face_vertices"]

def rotations_from_quaternions(quaternions: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(n_frames, 3, 3)`` of unit quaternions ``(n_frames, 4)`` (x, y, z, w)."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(quaternions, dtype=float).reshape(-1, 4)
    return Rotation.from_quat(q).as_matrix() if len(q) else np.zeros((0, 3, 3))


def render_preview(track: Track, weights: Weights, rig: Rig, path, *, video=None,
                   keys: KeyShapes | None = None, rig_weights: np.ndarray | None = None,
                   rotations: np.ndarray | None = None, height: int | None = None, strip_height: int = 96,
                   backend: str = "auto", progress: bool = False, colours: np.ndarray | None = None,
                   pivot: np.ndarray | None = None) -> Path:
    """Write the preview MP4: source + landmarks | character, over a strip of the weights.

    Parameters
    ----------
    track : Track
        ``points (n_frames, n_landmarks, 2 or 3)`` in image pixels; sets the frame count and rate.
    weights : Weights
        ``values (n_frames, n_keys)``: the key weights shown in the strip.
    rig : Rig
        The character.
    path : str or Path
        Output ``.mp4`` (H.264, yuv420p), written atomically.
    video : str or Path, optional, keyword-only
        The source video; without it (or when missing) the landmarks are drawn on a dark canvas.
    keys : KeyShapes, optional, keyword-only
        Gives the regions: landmark and bar colours.
    rig_weights : (n_frames, n_targets) float, optional, keyword-only
        What drives the rig; default ``weights.values``, whose names must then be the rig's targets.
    rotations : (n_frames, 3, 3) float, optional, keyword-only
        Head rotations in glTF axes (see :func:`keyshape.schemes.head_rotations`); NaN frames hold the last one.
    height : int, optional, keyword-only
        Height of the picture row (the character panel is square); default the source video's
        height, kept between 360 and 720 pixels.
    strip_height : int, keyword-only
    backend : "auto", "gl" or "numpy", keyword-only
        See :func:`keyshape.render._backend.make_renderer`.
    progress : bool, keyword-only
    colours : (n_vertices, 3) float in [0, 1], optional, keyword-only
        The character's colour per vertex (default: clay).
    pivot : (3,) float, optional, keyword-only
        The point the head turns about (a full-body avatar's head joint); default the origin.

    The camera frames the face: the vertices the targets move and the rest of the mesh near
    them (a full-body avatar's head and hair, not its body).

    Returns
    -------
    Path
    """
    driving = _check_inputs(track, weights, rig, rig_weights, rotations)
    rotations = _hold_rotations(rotations, track.n_frames)
    source_height = _image_height(track, video)
    height = _even(np.clip(source_height, 360, 720) if height is None else height)
    sources = _source_frames(video, track, height)
    first = next(sources)
    split, width = first.shape[1], first.shape[1] + height
    strip = WeightStrip(weights.names, _channel_colours(weights.names, keys), width, _even(strip_height),
                        regions=_channel_regions(weights.names, keys))
    overlay = _LandmarkOverlay(track, keys, scale=first.shape[0] / source_height)
    canvas = np.zeros((height + strip.height, width, 3), np.uint8)
    with (
        atomic_path(path) as tmp,
        _CharacterView(rig, driving, rotations, height, backend, colours, pivot) as character,
        VideoWriter(tmp, width, height + strip.height, track.fps) as out,
    ):
        frames = _with_first(first, sources)
        for index, source in _progress(enumerate(frames), track.n_frames, progress):
            canvas[:height, :split] = overlay(source, index)
            canvas[:height, split:] = character(index)
            canvas[height:] = strip.draw(weights.values[index])
            out.write(canvas)
    return Path(path)


def face_vertices(rig: Rig) -> np.ndarray:
    """Indices of the rig's face: the vertices its targets move and those near them.

    "Near" is within 1.3 times the farthest moved vertex's distance from the moved vertices'
    centre: a head's cranium, hair and eyes, not the body of a full-body avatar. Every vertex
    when no target moves any.

    Returns
    -------
    (n_face,) int
    """
    moved = np.abs(rig.deltas).max(axis=(0, 2)) > 1e-6 if rig.n_targets else np.zeros(rig.n_vertices, bool)
    if not moved.any():
        return np.arange(rig.n_vertices)
    centre = (rig.vertices[moved].min(axis=0) + rig.vertices[moved].max(axis=0)) / 2
    distance = np.linalg.norm(rig.vertices - centre, axis=1)
    return np.flatnonzero(distance <= 1.3 * distance[moved].max())


def _check_inputs(track, weights, rig, rig_weights, rotations) -> np.ndarray:
    n = track.n_frames
    if n == 0:
        raise InputError("the track has no frames: nothing to preview")
    if weights.n_frames != n:
        raise InputError(f"weights have {weights.n_frames} frames but the track has {n}")
    if rig_weights is None:
        if tuple(weights.names) != tuple(rig.names):
            raise InputError(f"weights {list(weights.names)} do not name the rig's targets "
                             f"{list(rig.names)}: pass rig_weights (retarget first)")
        rig_weights = weights.values
    rig_weights = np.asarray(rig_weights, dtype=float)
    if rig_weights.shape != (n, rig.n_targets):
        raise InputError(f"rig_weights must have shape ({n}, {rig.n_targets}); got {rig_weights.shape}")
    if rotations is not None and np.shape(rotations) != (n, 3, 3):
        raise InputError(f"rotations must have shape ({n}, 3, 3); got {np.shape(rotations)}")
    return rig_weights


def _hold_rotations(rotations, n_frames: int) -> np.ndarray:
    """(n_frames, 3, 3): NaN frames hold the previous valid rotation (leading ones the first)."""
    if rotations is None:
        return np.tile(np.eye(3), (n_frames, 1, 1))
    rotations = np.asarray(rotations, dtype=float)
    valid = np.isfinite(rotations).all(axis=(1, 2))
    if not valid.any():
        return np.tile(np.eye(3), (n_frames, 1, 1))
    source = np.maximum.accumulate(np.where(valid, np.arange(n_frames), -1))
    source[source < 0] = np.flatnonzero(valid)[0]
    return rotations[source]


def _even(value: int) -> int:
    return max(2, int(value) // 2 * 2)


def _image_height(track: Track, video) -> float:
    """Height in pixels of the images the track's coordinates refer to."""
    if track.image_size is not None:
        return float(track.image_size[1])
    if video is not None and Path(video).is_file():
        from ..capture.video import probe

        return float(probe(video).height)
    return float(_canvas_size(track)[1])


def _canvas_size(track: Track) -> tuple[int, int]:
    """(width, height) of a blank canvas holding the landmarks when there is no video."""
    if track.image_size is not None:
        return track.image_size
    finite = track.points[track.valid][..., :2]
    if finite.size == 0:
        return 640, 480
    hi = np.nanmax(finite.reshape(-1, 2), axis=0)
    return int(np.ceil(hi[0] * 1.05)) + 1, int(np.ceil(hi[1] * 1.05)) + 1


def _source_frames(video, track: Track, height: int) -> Iterator[np.ndarray]:
    """Exactly ``track.n_frames`` pictures scaled to ``height``: the video frames the track's
    rows come from (``track.frame_index``: a take tracked from ``--start 24`` shows frame 24
    first), the last one held."""
    yielded, last = 0, None
    if video is not None and Path(video).is_file():
        from ..capture.video import iter_frames

        wanted = track.frame_index
        first = int(wanted[0])
        frames = iter_frames(video, start=first, end=int(wanted[-1]) + 1)
        try:
            for index, (_, rgb) in enumerate(frames, start=first):
                if yielded == track.n_frames:
                    break
                if index != wanted[yielded]:
                    continue
                last = resize_to_height(rgb, height)
                yielded += 1
                yield last
        finally:
            frames.close()
    if last is None:
        width, h = _canvas_size(track)
        last = np.full((height, _even(width * height / h), 3), 32, np.uint8)
    for _ in range(track.n_frames - yielded):
        yield last


def _with_first(first, rest) -> Iterator[np.ndarray]:
    yield first
    yield from rest


def _progress(iterable, total: int, enabled: bool):
    if not enabled:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc="preview", unit="frame", disable=None)  # None: only on a terminal


def _channel_colours(names, keys: KeyShapes | None) -> np.ndarray:
    """(n_channels, 3) uint8: the colour of each key's region (grey when unknown)."""
    if keys is None:
        return np.tile(np.array(region_palette(["whole"])["whole"], np.uint8), (len(names), 1))
    palette = region_palette(keys.regions)
    region_of = dict(zip(keys.names, keys.key_regions))
    return np.array([palette.get(region_of.get(n), OTHER_COLOUR) for n in names], np.uint8)


def _channel_regions(names, keys: KeyShapes | None) -> tuple:
    """The region of each channel that is a key (None for the others, and for all without keys)."""
    region_of = dict(zip(keys.names, keys.key_regions)) if keys is not None else {}
    return tuple(region_of.get(n) for n in names)


class _LandmarkOverlay:
    """Draws frame ``index``'s landmarks, coloured by region, and a caption.

    With the track's ``visibility``, a hidden landmark (visibility < 0.5: a hand over it, the side
    turned away) is drawn as a grey cross instead of a coloured dot, and a part hidden in the frame
    (:meth:`Track.hidden <keyshape.containers.Track.hidden>`: the mouth, an eye, or a key region)
    is named under the caption ("mouth hidden").
    """

    def __init__(self, track: Track, keys: KeyShapes | None, *, scale: float):
        self.track, self.scale = track, scale
        regions = keys.regions if keys is not None else {}
        self.colours = landmark_colours(regions, track.n_landmarks)
        self.radii = np.where((self.colours == OTHER_COLOUR).all(axis=1), 1.0, 1.6)
        self.edges = _contour_edges(track.n_landmarks)
        self.hidden = {name: track.hidden(ix) for name, ix in _hidden_parts(track.n_landmarks, regions).items()} \
            if track.visibility is not None else {}

    def __call__(self, image: np.ndarray, index: int) -> np.ndarray:
        points = self.track.points[index, :, :2] * self.scale
        valid = bool(self.track.valid[index])
        out = image
        if valid:
            hidden = self.track.seen[index] < 0.5  # (n_landmarks,) bool
            colours = np.where(hidden[:, None], np.array(HIDDEN_COLOUR, np.uint8), self.colours)
            out = draw_landmarks(image, points, colours, edges=self.edges, radius=np.where(hidden, 1.0, self.radii))
            out = draw_crosses(out, points[hidden], HIDDEN_COLOUR) if hidden.any() else out
        label = (f"frame {self.track.frame_index[index]}   {self.track.time[index]:6.2f} s"
                 + ("" if valid else "   no face"))
        out = caption(out, label)
        hidden = [name for name, frames in self.hidden.items() if valid and frames[index]]
        return caption(out, ", ".join(hidden) + " hidden", xy=(8, 28)) if hidden else out


def _hidden_parts(n_landmarks: int, regions: dict) -> dict[str, np.ndarray]:
    """The parts whose hiding the preview names: MediaPipe's mouth and eyes, else the key regions."""
    if n_landmarks in (468, 478):
        contours = mediapipe_scheme()["contours"]
        return {label: np.asarray(contours[name]) for label, name in
                (("mouth", "lips"), ("right eye", "right_eye"), ("left eye", "left_eye"))}
    return {name: np.asarray(ix) for name, ix in regions.items()}


def _contour_edges(n_landmarks: int) -> np.ndarray | None:
    """MediaPipe's contour segments (eyes, brows, lips, irises, oval) for its landmark counts."""
    if n_landmarks not in (468, 478):
        return None
    edges = [e for name, pairs in mediapipe_scheme()["contour_edges"].items()
             if n_landmarks == 478 or "iris" not in name for e in pairs]
    return np.array(edges, dtype=np.int64).reshape(-1, 2)


class _CharacterView:
    """Renders the rig posed at frame ``index`` from a fixed camera framing its face over the take."""

    def __init__(self, rig: Rig, weights: np.ndarray, rotations: np.ndarray, size: int, backend: str,
                 colours: np.ndarray | None = None, pivot: np.ndarray | None = None):
        self.rig, self.weights, self.rotations = rig, weights, rotations
        self.pivot = np.zeros(3) if pivot is None else np.asarray(pivot, dtype=float).reshape(3)
        face = face_vertices(rig)
        sampled = self._pose(np.linspace(0, len(weights) - 1, 48).astype(int))
        self.camera = frame_points(sampled[:, face], fov_deg=25.0, margin=1.12)
        self.renderer = make_renderer(rig.faces, size, size, n_vertices=rig.n_vertices, backend=backend,
                                      colours=colours)

    def _pose(self, frames: np.ndarray) -> np.ndarray:
        """Posed and rotated vertices ``(len(frames), n_vertices, 3)``."""
        posed = self.rig.pose(self.weights[frames]) - self.pivot
        # f: frame, i/j: axis, v: vertex — the head's rotation, about its pivot
        return np.einsum("fij,fvj->fvi", self.rotations[frames], posed) + self.pivot

    def __call__(self, index: int) -> np.ndarray:
        image = self.renderer.render(self._pose(np.array([index]))[0], self.camera)
        return caption(image, "character")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.renderer.close()
