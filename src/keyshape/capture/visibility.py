"""Per-landmark visibility from the video: a hand or an object over the face, a side turned away.

MediaPipe places all 478 landmarks in every frame, also under a hand, and says nothing about it.
:func:`estimate_visibility` measures two things per landmark and frame and returns a visibility
in [0, 1] (1 = seen):

* **Appearance.** A small colour patch is read around the landmark (a 5 x 5 grid spanning
  ``PATCH_RADIUS`` inter-ocular distances, turned with the eye line, so it follows the face).
  A landmark is compared with *exemplars*: its own patches in up to ``N_EXEMPLARS`` frames of the
  take where it looked most typical (nearest the take's median patch, read on a sample of at most
  ``N_SAMPLE`` frames). The distance to the nearest exemplar, as a robust z-score (median and
  MAD over the sample), is large when something else is in front of the landmark: a hand over the
  mouth hides the lips' colour and the mouth line, fingers over an eye its lashes and iris. The
  nearest of several exemplars, not one reference frame, keeps an open mouth from counting as
  hidden. Eyes shut in laughter can be a third of a take, too many to be typical: the eyes and
  brows also have exemplars from the typical half of the frames with closed and with open eyes
  (the tracked lids tell which), and count by the nearer set. The z-scores are averaged over each
  landmark's nearest neighbours on the face (occluders are larger than a landmark) and over three
  frames.
* **Facing.** For a 3-D track, the normal of the face mesh at the landmark (from the tracked
  points) tells whether its side of the face is turned away from the camera: back-facing
  landmarks are hidden by the head itself.

The method assumes an occluder hides a part of the face in fewer than half of the frames (the
median patch is then the part's own). It is measured on the embedded clip against hand labels in
``benchmarks/occlusion_labels.json`` (see docs/occlusion.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..schemes import eye_corners, face_triangles, part_contours

__all__ = ["estimate_visibility", "visibility_from_patches", "read_patches", "sample_frames", "facing"]

PATCH_RADIUS = 0.06  # of the inter-ocular distance
PATCH_GRID = 5
N_SAMPLE = 300
N_EXEMPLARS = 16
N_STRATA = 2  # the eyes' and brows' exemplars also come from this many strata of eye openness
N_NEIGHBOURS = 8
Z_HIDDEN = 0.9  # the robust z-score (smoothed) at which visibility is 0.5
Z_WIDTH = 0.2
FACING_HIDDEN = 0.15  # a landmark whose normal points this far away from the camera is hidden
CHUNK = 64  # frames scored at once (memory: CHUNK x n_landmarks x N_EXEMPLARS patches)
CHUNK_FACING = 256  # frames whose mesh normals are summed at once (about 150 kB a frame of temporaries)
CHUNK_SCORE = 4096  # frames turned from z-scores into visibility at once
MEDIAN_COLUMNS = 32  # landmarks whose median over the take is taken at once


def _grid() -> np.ndarray:
    """(PATCH_GRID**2, 2) offsets in [-1, 1]."""
    g = np.linspace(-1.0, 1.0, PATCH_GRID)
    gx, gy = np.meshgrid(g, g)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """image (h, w, c) sampled at float pixel positions x, y (any shape) -> (*x.shape, c)."""
    h, w = image.shape[:2]
    x = np.clip(x, 0, w - 1.001)
    y = np.clip(y, 0, h - 1.001)
    x0, y0 = x.astype(np.int64), y.astype(np.int64)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    pixels, at = image.reshape(h * w, -1), y0 * w + x0  # np.take of pixel rows: 4x faster than image[y0, x0]

    def corner(offset: int) -> np.ndarray:  # (*x.shape, c) float64
        return np.take(pixels, at + offset, axis=0).astype(np.float64)

    gx = 1 - fx
    top = corner(0) * gx + corner(1) * fx
    bottom = corner(w) * gx + corner(w + 1) * fx
    return top * (1 - fy) + bottom * fy


def read_patches(rgb: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Colour patches around every landmark of one frame.

    Parameters
    ----------
    rgb : (height, width, 3) uint8
    points : (n_landmarks, 2 or 3) float, pixels (NaN: no face)

    Returns
    -------
    (n_landmarks, PATCH_GRID**2, 3) float32 in [0, 1]; NaN where ``points`` is NaN.
    """
    xy = np.asarray(points, dtype=float)[:, :2]
    if not np.isfinite(xy).all():
        return np.full((len(xy), PATCH_GRID ** 2, 3), np.nan, np.float32)
    corners = eye_corners(len(xy))
    span = xy[corners[1]] - xy[corners[0]] if corners else np.ptp(xy, axis=0) * [1.0, 0.0]
    size = max(float(np.linalg.norm(span)), 1e-6)
    c, s = span / size
    rotation = np.array([[c, -s], [s, c]])
    offsets = _grid() * PATCH_RADIUS * size @ rotation.T  # (g, 2)
    at = xy[:, None, :] + offsets[None]  # (n_landmarks, g, 2)
    return (_bilinear(rgb, at[..., 0], at[..., 1]) / 255.0).astype(np.float32)  # only the samples as floats


def _distances(patches: np.ndarray, exemplars: np.ndarray, landmarks: np.ndarray | None = None) -> np.ndarray:
    """RMS distance of each landmark's patch to its nearest exemplar.

    patches : (n_frames, n_all, g, 3), read ``CHUNK`` frames at a time; exemplars : (n_landmarks,
    n_ex, g, 3) of ``landmarks`` (n_landmarks,) int, default all -> (n_frames, n_landmarks);
    NaN patches give NaN (a frame with no face)
    """
    n_frames, n_landmarks = patches.shape[0], exemplars.shape[0]
    out = np.empty((n_frames, n_landmarks), np.float32)
    ex = exemplars.reshape(n_landmarks, exemplars.shape[1], -1).astype(np.float32)
    ex_sq = (ex ** 2).sum(axis=2)  # (l, e)
    for at in range(0, n_frames, CHUNK):
        x = np.asarray(patches[at:at + CHUNK])
        x = (x if landmarks is None else x[:, landmarks]).reshape(-1, n_landmarks, ex.shape[2]).astype(np.float32)
        # |x - e|^2 = |x|^2 + |e|^2 - 2 x.e;  f: frame, l: landmark, e: exemplar, g: grid x colour
        cross = np.matmul(x.transpose(1, 0, 2), ex.transpose(0, 2, 1)).transpose(1, 0, 2)  # (f, l, e)
        sq = (x ** 2).sum(axis=2)[:, :, None] + ex_sq[None] - 2 * cross
        out[at:at + CHUNK] = np.sqrt(np.maximum(sq.min(axis=2), 0.0) / ex.shape[2])
    return out


class _Reference:
    """Per-landmark exemplar patches and the robust scale of distances to them, from a sample.

    The exemplars are the landmark's patches in its typical half of the sample (nearest the
    median patch): an occluder that covers a part in fewer than half of the frames is never one.
    With the sample's landmarks, the eyes and brows also get exemplars per stratum of their local
    shape (:func:`_strata`), the typical half of each, and a patch counts by the nearer of the two
    sets (the smaller z-score): a closed eye is compared with the take's closed eyes too, so eyes
    shut in laughter (a third of the embedded clip) do not read as hidden, while a hand over an
    eye is far from both. The mouth is not stratified: MediaPipe's guess of the lips under a hand
    is a shape of its own, so a hand over the mouth would make a stratum and its exemplars
    (measured on the labelled clip: covered mouths found hidden fall from 93.5 % to 69 %).
    """

    def __init__(self, sample: np.ndarray, points: np.ndarray | None = None):
        # sample (n_sample, n_landmarks, g, 3), finite frames; points (n_sample, n_landmarks, >= 2)
        self._sets = [_Exemplars(sample, np.zeros(sample.shape[:2], np.int64))]
        upper = _upper_face(sample.shape[1]) if points is not None else None
        if upper is not None and len(sample) >= 2 * N_STRATA:
            self.upper = upper
            self._sets.append(_Exemplars(sample, _strata(points, upper), upper))

    def z(self, patches: np.ndarray) -> np.ndarray:
        """(n_frames, n_landmarks) robust z-scores of the distance to the nearest exemplar."""
        z = self._sets[0].z(patches)
        if len(self._sets) > 1:
            z[:, self.upper] = np.minimum(z[:, self.upper], self._sets[1].z(patches))
        return z


class _Exemplars:
    """``N_EXEMPLARS`` exemplar patches per landmark of ``landmarks`` (default all), spread over its
    strata ``(n_sample, n_landmarks)``, and the robust scale (median, MAD) of the sample's
    distances to them."""

    def __init__(self, sample: np.ndarray, strata: np.ndarray, landmarks: np.ndarray | None = None):
        self.landmarks = landmarks
        picks = []
        for i, j in enumerate(np.arange(sample.shape[1]) if landmarks is None else landmarks):
            levels = np.unique(strata[:, i])
            per = -(-N_EXEMPLARS // len(levels))  # ceil
            chosen = []
            for level in levels:
                frames = np.flatnonzero(strata[:, i] == level)
                patch = sample[frames, j]
                first = np.sqrt(((patch - np.median(patch, axis=0)) ** 2).mean(axis=(1, 2)))
                typical = frames[first <= np.median(first)]
                chosen.append(typical[np.linspace(0, len(typical) - 1, per).astype(int)])
            picks.append(sample[np.concatenate(chosen)[:N_EXEMPLARS], j])
        self.exemplars = np.stack(picks)  # (n_landmarks, n_ex, g, 3)
        d = self.distances(sample)
        self.median = np.median(d, axis=0)
        self.mad = np.median(np.abs(d - self.median), axis=0) + 1e-4

    def distances(self, patches) -> np.ndarray:
        return _distances(patches, self.exemplars, self.landmarks)

    def z(self, patches) -> np.ndarray:
        return (self.distances(patches) - self.median) / self.mad


def _upper_face(n_landmarks: int) -> np.ndarray | None:
    """The brows' and eyes' landmarks (the upper region of ``upper-lower``), or None for a scheme
    without named eyes."""
    from ..schemes import resolve_regions

    if part_contours(n_landmarks) is None:
        return None
    return np.asarray(resolve_regions("upper-lower", n_landmarks)["upper"])


def _strata(points: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """(n_sample, len(upper)) int in [0, N_STRATA): each sampled frame's quantile bin of how open
    its eyes are (each eye outline's height over its width, both eyes' mean), the same for every
    landmark of the upper face. (Binning the brows by their height instead made them no better:
    a furrowed brow is not an eye's closing.)"""
    xy = np.asarray(points, dtype=float)[:, :, :2]
    contours = part_contours(xy.shape[1])
    openness = np.zeros(len(xy))
    for side in ("left", "right"):
        ring = xy[:, contours[f"{side}_eye"]]
        sv = np.linalg.svd(ring - ring.mean(axis=1, keepdims=True), compute_uv=False)  # along, across the eye
        openness += sv[:, 1] / np.maximum(sv[:, 0], 1e-9)
    edges = np.quantile(openness, np.linspace(0, 1, N_STRATA + 1)[1:-1])
    return np.repeat(np.searchsorted(edges, openness)[:, None], len(upper), axis=1)


def _median_shape(points: np.ndarray, dtype=None) -> np.ndarray:
    """``np.nanmedian(points, axis=0)`` (in ``dtype``), a few landmarks at a time: the same numbers
    without a copy of the whole take. points : (n_frames, n_landmarks, d) -> (n_landmarks, d)"""
    return np.concatenate([np.nanmedian(np.asarray(points[:, j:j + MEDIAN_COLUMNS], dtype=dtype), axis=0)
                           for j in range(0, points.shape[1], MEDIAN_COLUMNS)])


def _neighbours(shape: np.ndarray) -> np.ndarray:
    """(n_landmarks, N_NEIGHBOURS + 1) each landmark and its nearest ones in ``shape`` (n_landmarks, 2)."""
    d = np.linalg.norm(shape[:, None, :2] - shape[None, :, :2], axis=-1)
    return np.argsort(d, axis=1)[:, :N_NEIGHBOURS + 1]


def _smooth(z: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Average z (n_frames, n_landmarks) over the landmark's neighbours and three frames."""
    z = np.nan_to_num(z, nan=0.0)[:, neighbours].mean(axis=2)
    padded = np.concatenate([z[:1], z, z[-1:]])
    return (padded[:-2] + padded[1:-1] + padded[2:]) / 3.0


def _outward(tris: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """The triangles (n_faces, 3) wound so their normals point out of the head in ``shape``.

    The mesh's winding is not consistent; "out" is away from a point half a face width behind
    the face's centre (image axes: z away from the camera).
    """
    centre = np.nanmean(shape, axis=0) + [0.0, 0.0, 0.5 * np.ptp(shape[:, 0])]
    a, b, c = (shape[tris[:, k]] for k in range(3))
    out = np.einsum("fd,fd->f", np.cross(b - a, c - a), (a + b + c) / 3 - centre)
    return np.where((out < 0)[:, None], tris[:, ::-1], tris)


def _toward(p: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """The z of the unit vertex normals toward the camera: p (n_frames, >= 468, 3) -> (n_frames, 468)."""
    # the corners' coordinates, one contiguous (n_frames, n_faces) array each (np.take: fast)
    coords = [np.ascontiguousarray(p[..., d]) for d in range(3)]
    a, b, c = ([np.take(q, tris[:, k], axis=1) for q in coords] for k in range(3))
    u, v = [bd - ad for ad, bd in zip(a, b)], [cd - ad for ad, cd in zip(a, c)]
    # u x v, the area-weighted normal of each triangle, term by term as np.cross computes it
    normals = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])
    # each vertex sums the normals of its triangles: bins frame * 468 + vertex, in the order
    # (frame, corner, face), so the sums are those of np.add.at corner by corner (and 5x faster)
    n_frames, n_faces = normals[0].shape
    bins = (np.arange(n_frames)[:, None, None] * 468 + tris.T[None]).ravel()
    vertex = np.stack([np.bincount(bins, np.broadcast_to(n[:, None], (n_frames, 3, n_faces)).ravel(),
                                   minlength=n_frames * 468) for n in normals], axis=-1)
    vertex = vertex.reshape(n_frames, 468, 3).astype(float, copy=False)  # int64 for no frame
    vertex /= np.linalg.norm(vertex, axis=-1, keepdims=True) + 1e-12
    return -vertex[..., 2]


def facing(points: np.ndarray) -> np.ndarray:
    """How much each landmark faces the camera: the z of its unit mesh normal, toward the camera.

    points : (n_frames, 478 or 468, 3) in image axes (z away from the camera)
    -> (n_frames, n_landmarks) in [-1, 1]: 1 faces the camera, < 0 is turned away. Iris points
    (468..477) take their eye's mean.
    """
    return _facing_rows(points, _outward(face_triangles(), _median_shape(points, float)))


def _facing_rows(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """:func:`facing` of ``points`` (n_frames, n_landmarks, 3) with the take's ``tris`` (:func:`_outward`)."""
    toward = np.concatenate([_toward(np.asarray(points[at:at + CHUNK_FACING], dtype=float), tris)
                             for at in range(0, max(len(points), 1), CHUNK_FACING)])
    if points.shape[1] > 468:
        iris = toward.mean(axis=1, keepdims=True).repeat(points.shape[1] - 468, axis=1)  # NaN frames stay NaN
        toward = np.concatenate([toward, iris], axis=1)
    return toward


def sample_frames(points: np.ndarray) -> np.ndarray:
    """The frames whose patches make the exemplars: up to ``N_SAMPLE`` of the frames with a face,
    evenly spread. points : (n_frames, n_landmarks, 2 or 3) -> (n_sample,) int, increasing."""
    points = np.asarray(points)
    valid = np.flatnonzero(np.isfinite(points[:, :, :2]).all(axis=(1, 2)))
    return np.unique(valid[np.linspace(0, len(valid) - 1, min(N_SAMPLE, len(valid))).astype(int)])


def visibility_from_patches(patches_sample: np.ndarray, patches: np.ndarray, points: np.ndarray,
                            *, neighbours: np.ndarray | None = None, unread: np.ndarray | None = None,
                            sample: np.ndarray | None = None) -> np.ndarray:
    """Visibility from patches: the core of :func:`estimate_visibility`, without video decoding.

    Parameters
    ----------
    patches_sample : (n_sample, n_landmarks, g, 3) float, patches of frames with a face
    patches : (n_frames, n_landmarks, g, 3) float, the frames to score (NaN: no face); read a
        chunk of frames at a time (``patches[i:j]``), so it may be anything with ``shape`` that
        slices so (a view of a spool on disk)
    points : (n_frames, n_landmarks, 2 or 3) float, the track's pixels
    unread : (n_frames,) bool, optional, keyword-only
        Frames whose patches were not read (a live recording's calibration frames): scored as
        a frame without a face is, typical.
    sample : (n_sample,) int, optional, keyword-only
        The frames of ``points`` that ``patches_sample`` comes from (:func:`sample_frames`): the
        exemplars are then drawn per stratum of local shape (see :class:`_Reference`).

    Returns
    -------
    (n_frames, n_landmarks) float32 in [0, 1]; 1 where there is no face (nothing to hide).
    """
    z = _Reference(patches_sample, None if sample is None else np.asarray(points)[sample]).z(patches)
    if unread is not None:
        z[np.asarray(unread, bool)] = np.nan
    return _visibility(z, points, neighbours)


def _visibility(z: np.ndarray, points: np.ndarray, neighbours: np.ndarray | None = None) -> np.ndarray:
    """z (n_frames, n_landmarks) appearance z-scores and the track -> visibility in [0, 1],
    ``CHUNK_SCORE`` frames at a time (memory does not grow with the take beyond z and the result)."""
    if neighbours is None:
        neighbours = _neighbours(_median_shape(points))
    tris = None
    if points.shape[2] == 3 and points.shape[1] in (468, 478):
        tris = _outward(face_triangles(), _median_shape(points, float))
    seen = np.empty(z.shape, np.float32)
    for at in range(0, len(z), CHUNK_SCORE):
        seen[at:at + CHUNK_SCORE] = _seen(z, points, neighbours, tris, at, min(at + CHUNK_SCORE, len(z)))
    return seen


def _seen(z: np.ndarray, points: np.ndarray, neighbours: np.ndarray, tris: np.ndarray | None,
          at: int, stop: int) -> np.ndarray:
    """The visibility of frames ``at <= i < stop`` (the smoothing reads one frame either side)."""
    lo, hi = max(at - 1, 0), min(stop + 1, len(z))
    smoothed = _smooth(z[lo:hi], neighbours)[at - lo:stop - lo]
    seen = 1.0 / (1.0 + np.exp(np.clip((smoothed - Z_HIDDEN) / Z_WIDTH, -50, 50)))
    rows = points[at:stop]
    if tris is not None:
        seen = seen * np.clip((_facing_rows(rows, tris) + FACING_HIDDEN) / FACING_HIDDEN, 0.0, 1.0)
    seen[~np.isfinite(rows).all(axis=(1, 2))] = 1.0
    return seen.astype(np.float32)


def estimate_visibility(path: str | Path, points: np.ndarray, *, start: int = 0, end: int | None = None,
                        fps: float | None = None) -> np.ndarray:
    """Per-landmark visibility of a tracked take, read again from its video.

    Parameters
    ----------
    path : the video (or image folder) the track was made from
    points : (n_frames, n_landmarks, 2 or 3) float, its track in pixels (NaN frames: no face);
        row i is the i-th frame decoded with ``start``, ``end`` and ``fps``, as in tracking
    start, end, fps : the range and rate the track was made with

    Returns
    -------
    visibility : (n_frames, n_landmarks) float32 in [0, 1]

    The video is decoded twice: once for a sample of frames (the exemplars), once for all.
    """
    from .video import iter_frames

    points = np.asarray(points)
    sample = set(sample_frames(points).tolist())
    sampled = [read_patches(rgb, points[i]) for i, (_, rgb) in zip(range(len(points)), iter_frames(
        path, start=start, end=end, fps=fps)) if i in sample]
    reference = _Reference(np.stack(sampled), points[sorted(sample)])
    z = np.zeros(points.shape[:2], np.float32)  # a video that ends early: the rest counts as seen
    chunk: list[np.ndarray] = []
    done = 0
    for i, (_, rgb) in zip(range(len(points)), iter_frames(path, start=start, end=end, fps=fps)):
        chunk.append(read_patches(rgb, points[i]))
        if len(chunk) == CHUNK:
            z[done:done + CHUNK] = reference.z(np.stack(chunk))
            done, chunk = done + CHUNK, []
    if chunk:
        z[done:done + len(chunk)] = reference.z(np.stack(chunk))
    return _visibility(z, points)
