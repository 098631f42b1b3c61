"""Core data types: small frozen dataclasses that label numpy arrays.

Every stage of the pipeline passes these around::

    Track ──align──▶ Track (canonical) + Poses ──keys──▶ KeyShapes ──solve──▶ Weights
    Weights + Rig ──retarget──▶ animation

Arrays are validated once, in ``__post_init__``, made read-only and then trusted.
A frame with no face is a NaN frame in ``Track.points``; no separate mask is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .exceptions import InputError

__all__ = ["Track", "Poses", "KeyShapes", "Weights", "Rig", "blend"]


def _frozen(array, dtype=float) -> np.ndarray:
    out = np.array(array, dtype=dtype, copy=True)
    out.flags.writeable = False
    return out


def _frozen_owner(array) -> bool:
    """A read-only float64 ndarray owning its data, or a read-only view of one (a frozen Track's
    slice): nothing holds it writable, so it needs no copy."""
    if not isinstance(array, np.ndarray) or array.dtype != np.float64 or array.flags.writeable:
        return False
    base = array
    while isinstance(base.base, np.ndarray):
        base = base.base
    return base.base is None and not base.flags.writeable


def blend(base: np.ndarray, deltas: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Blendshape interpolation ``base + Σ_k w_k · delta_k`` (the paper's Eq. 1, delta form).

    Parameters
    ----------
    base : (n_points, n_dims) float
    deltas : (n_keys, n_points, n_dims) float
    weights : (n_frames, n_keys) float

    Returns
    -------
    (n_frames, n_points, n_dims) float

    Examples
    --------
    >>> base = np.zeros((2, 3)); deltas = np.ones((1, 2, 3))
    >>> blend(base, deltas, np.array([[0.5]]))[0, 0]
    array([0.5, 0.5, 0.5])
    """
    # f: frame, k: key, p: point, d: dimension
    return base[None] + np.einsum("fk,kpd->fpd", weights, deltas)


def _frame_clock(n_frames: int, fps: float, frame_index, time) -> tuple[np.ndarray, np.ndarray]:
    """(frame_index (n_frames,) int, time (n_frames,) float), checked; defaults from ``fps``."""
    if frame_index is None:
        index = np.arange(n_frames, dtype=np.int64)
    else:
        index = np.asarray(frame_index)
        if index.shape != (n_frames,) or not (np.issubdtype(index.dtype, np.integer) or index.size == 0):
            raise InputError(f"frame_index must be ({n_frames},) int; got shape {index.shape}, {index.dtype}")
        if n_frames and (index[0] < 0 or (np.diff(index) <= 0).any()):
            raise InputError("frame_index must be >= 0 and strictly increasing")
    seconds = index / fps if time is None else np.asarray(time, dtype=float)
    if seconds.shape != (n_frames,) or not np.isfinite(seconds).all() or (np.diff(seconds) <= 0).any():
        raise InputError(f"time must be ({n_frames},) finite seconds, strictly increasing; got shape "
                         f"{seconds.shape}")
    return _frozen(index, dtype=np.int64), _frozen(seconds)


HIDDEN_SHARE = 0.3  # a region is hidden in a frame when more of its landmarks have visibility below 0.5


@dataclass(frozen=True, eq=False)
class Track:
    """A landmark performance.

    Attributes
    ----------
    points : (n_frames, n_landmarks, n_dims) float, n_dims in {2, 3}
        x and y in pixels, z (if present) on the x scale. A frame with no face is all NaN.
    fps : float
    image_size : (width, height) or None
    blendshapes : (n_frames, n_scores) float or None
        MediaPipe's ARKit-style scores, NaN where no face.
    blendshape_names : tuple of str
    head_matrix : (n_frames, 4, 4) float or None
        MediaPipe's facial transformation matrix, NaN where no face.
    frame_index : (n_frames,) int
        The source video's frame number of each row (``--start 24``: 24, 25, ...); default
        0, 1, ...; strictly increasing.
    time : (n_frames,) float
        The source's presentation time of each row in seconds (variable frame rate clips keep
        their real timing); default ``frame_index / fps``; strictly increasing.
    visibility : (n_frames, n_landmarks) float in [0, 1] or None
        How visible each landmark is (1 seen, 0 hidden by a hand, an object or the head turned
        away), estimated from the video (:mod:`keyshape.capture.visibility`); None: all seen.
    """

    points: np.ndarray
    fps: float
    image_size: tuple[int, int] | None = None
    blendshapes: np.ndarray | None = None
    blendshape_names: tuple[str, ...] = ()
    head_matrix: np.ndarray | None = None
    frame_index: np.ndarray | None = None
    time: np.ndarray | None = None
    visibility: np.ndarray | None = None

    def __post_init__(self):
        points = self.points
        if not _frozen_owner(points):  # a read-only float array owning its data is frozen already
            points = np.array(points, dtype=float)  # our own copy, frozen below
        if points.ndim != 3 or points.shape[2] not in (2, 3):
            raise InputError(
                f"points must have shape (n_frames, n_landmarks, 2 or 3); got {points.shape}"
            )
        fps = float(self.fps)
        if not np.isfinite(fps) or fps <= 0:
            raise InputError(f"fps must be a positive number; got {self.fps!r}")
        # A frame is either fully present or fully missing; inf is missing as NaN is.
        partial = ~np.isfinite(points).all(axis=(1, 2))
        if partial.any():
            points = points if points.flags.writeable else points.copy()
            points[partial] = np.nan
        points.flags.writeable = False  # frozen as _frozen would, without a second copy
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "fps", fps)
        index, time = _frame_clock(points.shape[0], fps, self.frame_index, self.time)
        object.__setattr__(self, "frame_index", index)
        object.__setattr__(self, "time", time)
        if self.image_size is not None:
            object.__setattr__(self, "image_size", tuple(int(v) for v in self.image_size))
        if self.blendshapes is not None:
            scores = np.asarray(self.blendshapes, dtype=float)
            if scores.ndim != 2 or scores.shape[0] != points.shape[0]:
                raise InputError(
                    f"blendshapes must have shape ({points.shape[0]}, n_scores); got {scores.shape}"
                )
            object.__setattr__(self, "blendshapes", _frozen(scores))
        object.__setattr__(self, "blendshape_names", tuple(self.blendshape_names))
        if self.head_matrix is not None:
            mats = np.asarray(self.head_matrix, dtype=float)
            if mats.shape != (points.shape[0], 4, 4):
                raise InputError(
                    f"head_matrix must have shape ({points.shape[0]}, 4, 4); got {mats.shape}"
                )
            object.__setattr__(self, "head_matrix", _frozen(mats))
        if self.visibility is not None:
            seen = np.asarray(self.visibility, dtype=float)
            if seen.shape != points.shape[:2] or not ((seen >= 0) & (seen <= 1)).all():
                raise InputError(f"visibility must be {points.shape[:2]} values in [0, 1]; got shape "
                                 f"{seen.shape}")
            object.__setattr__(self, "visibility", _frozen(seen))

    n_frames = property(lambda self: self.points.shape[0])
    n_landmarks = property(lambda self: self.points.shape[1])
    n_dims = property(lambda self: self.points.shape[2])

    @property
    def valid(self) -> np.ndarray:
        """(n_frames,) bool: True where a face was found."""
        return ~np.isnan(self.points[:, 0, 0])

    @property
    def times(self) -> np.ndarray:
        """(n_frames,) float: seconds from the first frame (``time - time[0]``)."""
        return self.time - self.time[0] if self.n_frames else self.time

    @property
    def seen(self) -> np.ndarray:
        """(n_frames, n_landmarks) float: ``visibility``, or all ones when the track has none."""
        return self.visibility if self.visibility is not None else np.ones(self.points.shape[:2])

    def hidden(self, landmarks) -> np.ndarray:
        """(n_frames,) bool: frames in which the region of ``landmarks`` is hidden: more than
        ``HIDDEN_SHARE`` (30 %) of them have a visibility below 0.5 (a hand over the mouth or an
        eye). All False for a track without visibility. Key discovery takes no key from such a
        frame, the error measures skip it, the neutral is never one."""
        if self.visibility is None:
            return np.zeros(self.n_frames, dtype=bool)
        return (self.visibility[:, np.asarray(landmarks)] < 0.5).mean(axis=1) > HIDDEN_SHARE

    def with_points(self, points: np.ndarray) -> Track:
        """The same take with other landmark positions (e.g. aligned ones)."""
        return Track(points, self.fps, self.image_size, self.blendshapes, self.blendshape_names,
                     self.head_matrix, self.frame_index, self.time, self.visibility)

    def __getitem__(self, frames: slice) -> Track:
        """The frames ``frames`` (a slice) of the take, with their scores and head matrices."""
        if not isinstance(frames, slice):
            raise TypeError(f"a Track is sliced by frames, e.g. track[10:50]; got {frames!r}")
        pick = lambda a: None if a is None else a[frames]  # noqa: E731
        return Track(self.points[frames], self.fps, self.image_size, pick(self.blendshapes),
                     self.blendshape_names, pick(self.head_matrix), self.frame_index[frames],
                     self.time[frames], pick(self.visibility))

    def __repr__(self) -> str:
        return (
            f"Track(n_frames={self.n_frames}, n_landmarks={self.n_landmarks}, "
            f"n_dims={self.n_dims}, fps={self.fps:g}, valid={int(self.valid.sum())})"
        )


@dataclass(frozen=True, eq=False)
class Poses:
    """Per-frame similarity transforms from the canonical (neutral) face to the image.

    ``x_image = scale · R @ x_canonical + translation``; NaN where no face.

    Attributes
    ----------
    rotations : (n_frames, n_dims, n_dims) float, proper rotations (det = +1)
    translations : (n_frames, n_dims) float
    scales : (n_frames,) float
    """

    rotations: np.ndarray
    translations: np.ndarray
    scales: np.ndarray

    def __post_init__(self):
        rot = np.asarray(self.rotations, dtype=float)
        n = rot.shape[0] if rot.ndim == 3 else -1
        if rot.ndim != 3 or rot.shape[1] != rot.shape[2] or rot.shape[1] not in (2, 3):
            raise InputError(f"rotations must have shape (n_frames, d, d), d in (2, 3); got {rot.shape}")
        tra = np.asarray(self.translations, dtype=float)
        sca = np.asarray(self.scales, dtype=float)
        if tra.shape != (n, rot.shape[1]) or sca.shape != (n,):
            raise InputError(
                f"translations/scales must have shapes ({n}, {rot.shape[1]}) and ({n},); "
                f"got {tra.shape} and {sca.shape}"
            )
        object.__setattr__(self, "rotations", _frozen(rot))
        object.__setattr__(self, "translations", _frozen(tra))
        object.__setattr__(self, "scales", _frozen(sca))

    n_frames = property(lambda self: self.rotations.shape[0])
    n_dims = property(lambda self: self.rotations.shape[1])

    def to_image(self, canonical: np.ndarray) -> np.ndarray:
        """Map canonical points ``(n_frames, n_points, d)`` to image space."""
        # f: frame, i/j: dimension, p: point
        return (
            self.scales[:, None, None] * np.einsum("fij,fpj->fpi", self.rotations, canonical)
            + self.translations[:, None, :]
        )

    def __repr__(self) -> str:
        return f"Poses(n_frames={self.n_frames}, n_dims={self.n_dims})"


@dataclass(frozen=True, eq=False)
class KeyShapes:
    """A landmark-space rig: the neutral face and one delta per key shape.

    Each key belongs to one region; its delta is zero outside that region's landmarks,
    so ``pose`` with the solved weights is the reconstruction of the performance.

    Attributes
    ----------
    neutral : (n_landmarks, n_dims) float, aligned (canonical) coordinates
    deltas : (n_keys, n_landmarks, n_dims) float, key shape minus neutral, zero outside its region
    names : tuple of n_keys str, unique
    frames : (n_keys,) int, source frame of each key (a real frame of the performance)
    key_regions : tuple of n_keys str, the region of each key
    regions : dict str -> (n_region_landmarks,) int, landmark indices per region
    takes : tuple of n_keys str, the take each key comes from ("" for a single take)
    neutral_frame : int
    neutral_take : str
    method : str
    stable : (n_stable,) int or None, the landmarks the takes were aligned on
    mirror_of : tuple of n_keys str: for a mirrored key (its source key's shape reflected
        through the face's symmetry plane), the source key's name; "" for a key that is a frame
    """

    neutral: np.ndarray
    deltas: np.ndarray
    names: tuple[str, ...]
    frames: np.ndarray
    key_regions: tuple[str, ...]
    regions: dict[str, np.ndarray]
    takes: tuple[str, ...] = ()
    neutral_frame: int = 0
    neutral_take: str = ""
    method: str = ""
    stable: np.ndarray | None = field(default=None)
    mirror_of: tuple[str, ...] = ()

    def __post_init__(self):
        neutral = np.asarray(self.neutral, dtype=float)
        deltas = np.asarray(self.deltas, dtype=float).reshape(-1, *neutral.shape)
        k = deltas.shape[0]
        names, regions_of = tuple(self.names), tuple(self.key_regions)
        takes = tuple(self.takes) if self.takes else ("",) * k
        if len(names) != k or len(regions_of) != k or len(takes) != k or len(self.frames) != k:
            raise InputError(f"{k} key deltas need {k} names, frames, regions and takes")
        if len(set(names)) != k:
            raise InputError(f"key names must be unique; got {names}")
        regions = {str(r): _frozen(ix, dtype=int) for r, ix in self.regions.items()}
        unknown = set(regions_of) - set(regions)
        if unknown:
            raise InputError(f"keys refer to unknown regions {sorted(unknown)}")
        mirror_of = tuple(str(m) for m in self.mirror_of) if self.mirror_of else ("",) * k
        if len(mirror_of) != k:
            raise InputError(f"{k} key deltas need {k} mirror_of entries; got {len(mirror_of)}")
        for name, source in zip(names, mirror_of):
            if source and (source not in names or source == name or mirror_of[names.index(source)]):
                raise InputError(f"key {name!r} is marked as the mirror of {source!r}, which is not "
                                 f"another key of the set that is a frame")
        object.__setattr__(self, "mirror_of", mirror_of)
        object.__setattr__(self, "neutral", _frozen(neutral))
        object.__setattr__(self, "deltas", _frozen(deltas))
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "frames", _frozen(self.frames, dtype=int))
        object.__setattr__(self, "key_regions", regions_of)
        object.__setattr__(self, "regions", regions)
        object.__setattr__(self, "takes", takes)
        if self.stable is not None:
            object.__setattr__(self, "stable", _frozen(self.stable, dtype=int))

    n_keys = property(lambda self: self.deltas.shape[0])
    n_landmarks = property(lambda self: self.neutral.shape[0])
    n_dims = property(lambda self: self.neutral.shape[1])

    def keys_of(self, region: str) -> np.ndarray:
        """(n_region_keys,) int: indices of the keys belonging to ``region``."""
        return np.flatnonzero([r == region for r in self.key_regions])

    @property
    def mirrored(self) -> np.ndarray:
        """(n_keys,) bool: which keys are mirror images of another key."""
        return np.array([bool(m) for m in self.mirror_of], dtype=bool)

    def pose(self, weights: np.ndarray) -> np.ndarray:
        """Landmarks ``(n_frames, n_landmarks, n_dims)`` for weights ``(n_frames, n_keys)``."""
        return blend(self.neutral, self.deltas, np.nan_to_num(np.asarray(weights, dtype=float)))

    def __repr__(self) -> str:
        per = {r: len(self.keys_of(r)) for r in self.regions}
        mirrored = f", mirrored={int(self.mirrored.sum())}" if self.mirrored.any() else ""
        return f"KeyShapes(n_keys={self.n_keys}, per_region={per}{mirrored}, method={self.method!r})"


@dataclass(frozen=True, eq=False)
class Weights:
    """Blend weights over time, for key shapes or for rig targets (the names say which).

    Attributes
    ----------
    values : (n_frames, n_channels) float, NaN in frames with no estimate
    names : tuple of n_channels str
    fps : float
    frame_index : (n_frames,) int, the source frame of each row (as :class:`Track`'s)
    time : (n_frames,) float, the source time of each row in seconds (as :class:`Track`'s)
    """

    values: np.ndarray
    names: tuple[str, ...]
    fps: float
    frame_index: np.ndarray | None = None
    time: np.ndarray | None = None

    def __post_init__(self):
        values = np.asarray(self.values, dtype=float)
        names = tuple(str(n) for n in self.names)
        if values.ndim != 2 or values.shape[1] != len(names):
            raise InputError(
                f"weights must have shape (n_frames, {len(names)}) for {len(names)} names; "
                f"got {values.shape}"
            )
        if not float(self.fps) > 0 or not np.isfinite(float(self.fps)):
            raise InputError(f"fps must be a positive number; got {self.fps!r}")
        object.__setattr__(self, "values", _frozen(values))
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "fps", float(self.fps))
        index, time = _frame_clock(values.shape[0], float(self.fps), self.frame_index, self.time)
        object.__setattr__(self, "frame_index", index)
        object.__setattr__(self, "time", time)

    n_frames = property(lambda self: self.values.shape[0])
    n_channels = property(lambda self: self.values.shape[1])

    @property
    def times(self) -> np.ndarray:
        """(n_frames,) float: seconds from the first frame (``time - time[0]``)."""
        return self.time - self.time[0] if self.n_frames else self.time

    def with_values(self, values: np.ndarray, names) -> Weights:
        """Other channels over the same frames (same rate, frame numbers and times)."""
        return Weights(values, names, self.fps, self.frame_index, self.time)

    def __repr__(self) -> str:
        return f"Weights(n_frames={self.n_frames}, n_channels={self.n_channels}, fps={self.fps:g})"


@dataclass(frozen=True, eq=False)
class Rig:
    """A character's blendshapes: neutral mesh plus one delta per target.

    Attributes
    ----------
    vertices : (n_vertices, 3) float, the neutral mesh
    faces : (n_faces, 3) int, triangles
    deltas : (n_targets, n_vertices, 3) float, target minus neutral
    names : tuple of n_targets str
    """

    vertices: np.ndarray
    faces: np.ndarray
    deltas: np.ndarray
    names: tuple[str, ...]

    def __post_init__(self):
        vertices = np.asarray(self.vertices, dtype=float)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise InputError(f"vertices must have shape (n_vertices, 3); got {vertices.shape}")
        faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
            raise InputError(f"faces index vertices 0..{len(vertices) - 1}; got up to {faces.max()}")
        deltas = np.asarray(self.deltas, dtype=float).reshape(-1, *vertices.shape)
        names = tuple(self.names)
        if len(names) != deltas.shape[0]:
            raise InputError(f"{deltas.shape[0]} target deltas need as many names; got {len(names)}")
        object.__setattr__(self, "vertices", _frozen(vertices))
        object.__setattr__(self, "faces", _frozen(faces, dtype=np.int64))
        object.__setattr__(self, "deltas", _frozen(deltas))
        object.__setattr__(self, "names", names)

    n_vertices = property(lambda self: self.vertices.shape[0])
    n_targets = property(lambda self: self.deltas.shape[0])

    def pose(self, weights: np.ndarray) -> np.ndarray:
        """Deformed vertices ``(n_frames, n_vertices, 3)`` for weights ``(n_frames, n_targets)``."""
        return blend(self.vertices, self.deltas, np.nan_to_num(np.asarray(weights, dtype=float)))

    def __repr__(self) -> str:
        return f"Rig(n_vertices={self.n_vertices}, n_faces={len(self.faces)}, n_targets={self.n_targets})"
