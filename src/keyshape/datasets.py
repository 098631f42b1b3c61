"""Synthetic performances with known answers, in the style of scikit-learn's ``make_*``.

A random landmark-space rig (neutral face + per-region key deltas) is driven by known
non-negative weights, moved by known head poses and observed with pixel noise, so every
stage of the pipeline can be tested against the truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from .containers import Poses, Track, blend
from .exceptions import InputError

__all__ = ["Performance", "make_performance", "Occluder", "cut_out", "paste"]


@dataclass(frozen=True, eq=False)
class Performance:
    """A synthetic take and the truth behind it.

    Attributes
    ----------
    track : Track
        ``points (n_frames, n_landmarks, n_dims)`` in image pixels, NaN in dropped frames.
    true_weights : (n_frames, n_keys) float, >= 0
        Per region, each frame's weights sum to at most 1.
    true_poses : Poses
        Canonical → image: ``x_image = s · R @ x_canonical + t``.
    neutral : (n_landmarks, n_dims) float
        The canonical neutral face.
    key_deltas : (n_keys, n_landmarks, n_dims) float
        Key shape minus neutral, zero outside the key's region and on the stable landmarks.
    key_regions : tuple of n_keys str
    extreme_frames : (n_keys,) int
        ``extreme_frames[k]`` is a frame where key ``k`` has weight 1 and all others 0.
    neutral_frame : int
        A planted resting frame: all weights 0 (never dropped).
    regions : dict str -> (n_region_landmarks,) int
        ``"upper"`` and ``"lower"``, covering every landmark once.
    stable : (n_stable,) int
        Landmarks that move only with the head.
    """

    track: Track
    true_weights: np.ndarray
    true_poses: Poses
    neutral: np.ndarray
    key_deltas: np.ndarray
    key_regions: tuple[str, ...]
    extreme_frames: np.ndarray
    neutral_frame: int
    regions: dict[str, np.ndarray]
    stable: np.ndarray

    n_frames = property(lambda self: self.track.n_frames)
    n_keys = property(lambda self: self.key_deltas.shape[0])

    @property
    def canonical(self) -> np.ndarray:
        """(n_frames, n_landmarks, n_dims) float: the noiseless expression, head pose removed."""
        return blend(self.neutral, self.key_deltas, self.true_weights)


def make_performance(
    *,
    n_frames: int = 200,
    n_landmarks: int = 40,
    n_dims: int = 3,
    n_keys: int = 4,
    noise: float = 0.5,
    rotation_deg: float = 15.0,
    delta_scale: float = 8.0,
    n_missing: int = 0,
    fps: float = 30.0,
    random_state: int | np.random.Generator | None = 0,
) -> Performance:
    """Make a synthetic take: a known rig, known weights, random head poses and noise.

    Keys alternate between the ``"upper"`` and ``"lower"`` regions (key ``k`` belongs to
    region ``k % 2``). Weights are smooth, sparse bumps (each key active about a quarter of
    the time), scaled per region so that a frame's weights sum to at most 0.9; then one
    frame per key is set to that key alone at weight 1 (the planted extremes) and one
    frame to all weights 0 (the planted neutral). Head poses
    are smooth rotations up to ``rotation_deg`` (about all three axes in 3D, in-plane in
    2D), scales near 1 and translations near the image centre (320, 240).

    Parameters
    ----------
    n_frames, n_landmarks, n_dims, n_keys : int, keyword-only
        ``n_dims`` in {2, 3}; ``n_landmarks >= 12``; ``1 <= n_keys``, ``2 * n_keys <= n_frames``.
    noise : float
        Standard deviation of the i.i.d. Gaussian pixel noise.
    rotation_deg : float
        Amplitude of the head rotation, degrees.
    delta_scale : float
        RMS length of a key delta on its moving landmarks, canonical units (≈ pixels).
    n_missing : int
        Frames dropped (all NaN), never a planted extreme or the planted neutral.
    fps : float
    random_state : int, Generator or None
        Everything is deterministic given an int.

    Returns
    -------
    Performance

    Examples
    --------
    >>> perf = make_performance(n_frames=50, n_keys=4)
    >>> perf.track.points.shape, perf.true_weights.shape, perf.extreme_frames.shape
    ((50, 40, 3), (50, 4), (4,))
    """
    _check_sizes(n_frames, n_landmarks, n_dims, n_keys, n_missing)
    rng = np.random.default_rng(random_state)
    neutral = _neutral_face(rng, n_landmarks, n_dims)
    regions, stable = _regions(neutral)
    key_regions = tuple(("upper", "lower")[k % 2] for k in range(n_keys))
    deltas = _key_deltas(rng, neutral, regions, stable, key_regions, delta_scale)
    weights = _weights(rng, n_frames, key_regions)
    extremes = rng.choice(n_frames, size=n_keys + 1, replace=False)
    extremes, rest = extremes[:-1], int(extremes[-1])
    weights[extremes], weights[rest] = np.eye(n_keys), 0.0
    poses = _poses(rng, n_frames, n_dims, rotation_deg)
    points = poses.to_image(blend(neutral, deltas, weights))
    points += noise * rng.standard_normal(points.shape)
    free = np.setdiff1d(np.arange(n_frames), np.r_[extremes, rest])
    points[rng.choice(free, size=n_missing, replace=False)] = np.nan
    return Performance(
        track=Track(points, fps, image_size=(640, 480)),
        true_weights=weights,
        true_poses=poses,
        neutral=neutral,
        key_deltas=deltas,
        key_regions=key_regions,
        extreme_frames=extremes,
        neutral_frame=rest,
        regions=regions,
        stable=stable,
    )


def _check_sizes(n_frames, n_landmarks, n_dims, n_keys, n_missing) -> None:
    if n_dims not in (2, 3):
        raise InputError(f"n_dims must be 2 or 3; got {n_dims}")
    if n_landmarks < 12:
        raise InputError(f"n_landmarks must be at least 12; got {n_landmarks}")
    if n_keys < 1 or 2 * n_keys > n_frames:
        raise InputError(f"n_keys must be in 1..n_frames/2 = {n_frames // 2}; got {n_keys}")
    if not 0 <= n_missing <= n_frames - n_keys - 1:
        raise InputError(f"n_missing must be in 0..{n_frames - n_keys - 1}; got {n_missing}")


def _neutral_face(rng, n_landmarks: int, n_dims: int) -> np.ndarray:
    """Points on a face-sized half ellipsoid, ``(n_landmarks, n_dims)``; y grows downwards."""
    theta = rng.uniform(0, 2 * np.pi, n_landmarks)
    radius = np.sqrt(rng.uniform(0.05, 1.0, n_landmarks))
    x, y = 60 * radius * np.cos(theta), 80 * radius * np.sin(theta)
    z = -40 * np.sqrt(np.clip(1 - radius**2, 0, None))
    return np.stack([x, y, z], axis=1)[:, :n_dims]


def _regions(neutral: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Split at the median height: upper (brows, eyes) and lower (mouth, jaw); stable points.

    The stable landmarks are 8 well-spread upper points (farthest-point order), the
    "temples, eye corners and nose bridge" of this synthetic face.
    """
    order = np.argsort(neutral[:, 1], kind="stable")
    half = len(order) // 2
    upper, lower = np.sort(order[:half]), np.sort(order[half:])
    chosen = [upper[np.argmax(np.abs(neutral[upper, 0]))]]
    for _ in range(7):
        dist = ((neutral[upper, None] - neutral[chosen][None]) ** 2).sum(axis=2).min(axis=1)
        chosen.append(upper[np.argmax(dist)])
    return {"upper": upper, "lower": lower}, np.sort(np.array(chosen))


def _key_deltas(rng, neutral, regions, stable, key_regions, delta_scale) -> np.ndarray:
    """Smooth random displacement fields, ``(n_keys, n_landmarks, n_dims)``."""
    deltas = np.zeros((len(key_regions), *neutral.shape))
    for k, region in enumerate(key_regions):
        moving = np.setdiff1d(regions[region], stable)
        centre = neutral[rng.choice(moving)]
        falloff = np.exp(-((neutral[moving] - centre) ** 2).sum(axis=1) / (2 * 40.0**2))
        field = rng.standard_normal(neutral.shape[1]) + 0.6 * rng.standard_normal((moving.size, neutral.shape[1]))
        delta = field * falloff[:, None]
        deltas[k, moving] = delta * delta_scale / np.sqrt((delta**2).sum(axis=1).mean())
    return deltas


def _weights(rng, n_frames: int, key_regions: tuple[str, ...]) -> np.ndarray:
    """Smooth sparse non-negative weights ``(n_frames, n_keys)``; per region, sum <= 0.9."""
    raw = gaussian_filter1d(rng.standard_normal((n_frames, len(key_regions))), sigma=4, axis=0)
    raw /= raw.std(axis=0)
    weights = np.clip(raw - 0.7, 0, None)
    weights /= np.maximum(weights.max(axis=0), 1e-12)
    for region in set(key_regions):
        cols = [k for k, r in enumerate(key_regions) if r == region]
        total = weights[:, cols].sum(axis=1, keepdims=True)
        weights[:, cols] *= 0.9 / np.maximum(total, 0.9)
    return weights


def _poses(rng, n_frames: int, n_dims: int, rotation_deg: float) -> Poses:
    """Smooth head motion: rotations, scales near 1, translations near (320, 240)."""
    t = np.arange(n_frames)[:, None]
    phase, period = rng.uniform(0, 2 * np.pi, (1, 3)), rng.uniform(40, 120, (1, 3))
    angles = np.deg2rad(rotation_deg) * np.sin(2 * np.pi * t / period + phase)  # (n_frames, 3)
    rotations = _rotation_matrices(angles, n_dims)
    scales = 1.0 + 0.1 * np.sin(2 * np.pi * t[:, 0] / rng.uniform(60, 150) + rng.uniform(0, 6))
    centre = np.array([320.0, 240.0, 0.0])[:n_dims]
    translations = centre + 20 * np.sin(2 * np.pi * t / period[:, :n_dims] + phase[:, ::-1][:, :n_dims])
    return Poses(rotations, translations, scales)


def _rotation_matrices(angles: np.ndarray, n_dims: int) -> np.ndarray:
    """``(n_frames, n_dims, n_dims)`` from (pitch, yaw, roll) angles ``(n_frames, 3)``, R = Rz Ry Rx."""
    c, s = np.cos(angles), np.sin(angles)
    one, zero = np.ones(len(angles)), np.zeros(len(angles))
    rz = np.stack([[c[:, 2], -s[:, 2], zero], [s[:, 2], c[:, 2], zero], [zero, zero, one]])
    if n_dims == 2:
        return np.moveaxis(rz[:2, :2], -1, 0)
    ry = np.stack([[c[:, 1], zero, s[:, 1]], [zero, one, zero], [-s[:, 1], zero, c[:, 1]]])
    rx = np.stack([[one, zero, zero], [zero, c[:, 0], -s[:, 0]], [zero, s[:, 0], c[:, 0]]])
    # i/j/k/l: dimension, f: frame
    return np.einsum("ijf,jkf,klf->fil", rz, ry, rx)


@dataclass(frozen=True)
class Occluder:
    """A picture of an occluder cut out of a frame, to composite onto other takes at known places.

    pixels : (h, w, 3) uint8
    mask : (h, w) bool, the occluder's own pixels
    anchor : (2,) float, the point of the picture (x, y) to place on the target (e.g. the
        middle of the mouth it covered)
    scale : float, the face size (pixels) it was cut at: pasted on a face of size s, it is
        resized by s / scale
    """

    pixels: np.ndarray
    mask: np.ndarray
    anchor: np.ndarray
    scale: float


def cut_out(rgb: np.ndarray, mask: np.ndarray, anchor, scale: float) -> Occluder:
    """The masked part of ``rgb`` (h, w, 3) uint8, ``mask`` (h, w) bool, cropped to its bounding box;
    ``anchor`` (x, y) in ``rgb``'s pixels and ``scale`` as :class:`Occluder` says."""
    ys, xs = np.nonzero(mask)
    if not len(xs):
        raise ValueError("the mask is empty: nothing to cut out")
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    return Occluder(rgb[y0:y1, x0:x1].copy(), mask[y0:y1, x0:x1].copy(),
                    np.asarray(anchor, float) - (x0, y0), float(scale))


def paste(rgb: np.ndarray, occluder: Occluder, at, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``rgb`` (h, w, 3) uint8 with ``occluder`` composited so that its anchor lands on ``at`` (x, y),
    resized (nearest pixel) by ``scale / occluder.scale``.

    Returns the new picture (a copy) and its (h, w) bool mask of the pasted occluder's pixels: the
    truth of what is covered.
    """
    factor = scale / occluder.scale
    h, w = occluder.mask.shape
    out_h, out_w = max(1, round(h * factor)), max(1, round(w * factor))
    rows = np.minimum((np.arange(out_h) / factor).astype(int), h - 1)
    cols = np.minimum((np.arange(out_w) / factor).astype(int), w - 1)
    pixels, mask = occluder.pixels[np.ix_(rows, cols)], occluder.mask[np.ix_(rows, cols)]
    top_left = np.round(np.asarray(at, float) - occluder.anchor * factor).astype(int)  # (x, y)
    out, covered = rgb.copy(), np.zeros(rgb.shape[:2], bool)
    y0, x0 = max(top_left[1], 0), max(top_left[0], 0)
    y1, x1 = min(top_left[1] + out_h, rgb.shape[0]), min(top_left[0] + out_w, rgb.shape[1])
    if y1 <= y0 or x1 <= x0:
        return out, covered
    part = mask[y0 - top_left[1]:y1 - top_left[1], x0 - top_left[0]:x1 - top_left[0]]
    out[y0:y1, x0:x1][part] = pixels[y0 - top_left[1]:y1 - top_left[1], x0 - top_left[0]:x1 - top_left[0]][part]
    covered[y0:y1, x0:x1] = part
    return out, covered
