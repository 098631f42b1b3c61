"""Helpers of the tests (not of keyshape): a reference NNLS and a mesh over key-shape landmarks."""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from keyshape.containers import KeyShapes, Rig
from keyshape.exceptions import InputError
from keyshape.schemes import as_xyz, points_to_gltf


def nonnegative_fit(targets: np.ndarray, bases: np.ndarray) -> np.ndarray:
    """Exact non-negative least squares ``min_{w >= 0} |t_f - wᵀ B|²`` for every row ``t_f``.

    The problem is first reduced to ``n_keys`` equations through the Gram matrix
    ``G = B Bᵀ = Q Λ Qᵀ``: ``|t - wᵀB|² = |Λ^½ Qᵀ w - Λ^-½ Qᵀ B t|² + const``, then each
    frame is solved by Lawson-Hanson (``scipy.optimize.nnls``) on that small system.

    Parameters
    ----------
    targets : (n_frames, n_features) float
    bases : (n_keys, n_features) float

    Returns
    -------
    (n_frames, n_keys) float, >= 0

    Examples
    --------
    >>> nonnegative_fit(np.array([[1.0, -1.0]]), np.eye(2))
    array([[1., 0.]])
    """
    targets, bases = np.atleast_2d(targets), np.atleast_2d(bases)
    out = np.zeros((targets.shape[0], bases.shape[0]))
    if bases.shape[0] == 0 or targets.shape[0] == 0:
        return out
    lam, q = np.linalg.eigh(bases @ bases.T)
    keep = lam > lam.max() * 1e-12
    design = np.sqrt(lam[keep])[:, None] * q[:, keep].T  # Λ^½ Qᵀ, (n_kept, n_keys)
    rhs = (targets @ bases.T) @ q[:, keep] / np.sqrt(lam[keep])  # Λ^-½ Qᵀ B t, (n_frames, n_kept)
    for f, y in enumerate(rhs):
        out[f] = nnls(design, y, maxiter=50 * bases.shape[0])[0]
    return out


def rig_from_keyshapes(keys: KeyShapes, faces, *, size: float = 0.2) -> Rig:
    """The default character: a face mesh over the key shapes' neutral landmarks.

    Landmarks in canonical image coordinates (pixels; x right, y down, z on the x scale
    pointing away from the camera, as MediaPipe) become glTF coordinates (metres, +Y up,
    +Z toward the viewer): ``(x, y, z) -> (x, −y, −z)``, centred on the bounding box
    and scaled so the neutral face is ``size`` metres tall. Each key becomes one target,
    named after the key, its delta transformed the same way, so the key weights drive
    the mesh unchanged ("a smile for a smile").

    Parameters
    ----------
    keys : KeyShapes
        ``neutral (n_landmarks, 2 or 3)``; 2D landmarks get z = 0.
    faces : (n_faces, 3) int
        Triangles over the landmarks (e.g. MediaPipe's tesselation).
    size : float, keyword-only
        Face height in metres.

    Returns
    -------
    Rig
        ``n_vertices = n_landmarks``, ``names = keys.names``.

    Examples
    --------
    >>> keys = KeyShapes(np.array([[0., 0., 0.], [10., 0., 0.], [0., 20., 5.]]),
    ...                  np.array([[[0., 0., 0.], [0., 0., 0.], [0., 2., 0.]]]),
    ...                  ("open",), [3], ("whole",), {"whole": [0, 1, 2]})
    >>> rig = rig_from_keyshapes(keys, [[0, 1, 2]], size=0.2)
    >>> float(np.ptp(rig.vertices[:, 1])), rig.deltas[0, 2].tolist()
    (0.2, [0.0, -0.02, 0.0])
    """
    neutral, deltas = as_xyz(keys.neutral), as_xyz(keys.deltas)
    faces = _check_faces(faces, len(neutral))
    if not np.isfinite(neutral).all() or not np.isfinite(deltas).all():
        raise InputError("key shapes must be finite to build a rig")
    height = np.ptp(neutral[:, 1])
    if not size > 0 or height <= 0:
        raise InputError(f"size must be > 0 and the neutral face must have height; got size={size!r}, "
                         f"height={height:g} px")
    scale = size / height
    centre = (neutral.min(axis=0) + neutral.max(axis=0)) / 2
    vertices = points_to_gltf(neutral - centre) * scale + 0.0  # + 0.0: no negative zeros
    return Rig(vertices, faces, points_to_gltf(deltas) * scale + 0.0, tuple(keys.names))


def _check_faces(faces, n_vertices: int) -> np.ndarray:
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise InputError(f"faces must be an (n_faces, 3) int array; got shape {faces.shape}, {faces.dtype}")
    if faces.size and (faces.min() < 0 or faces.max() >= n_vertices):
        raise InputError(f"faces must index landmarks 0..{n_vertices - 1}; got {faces.min()}..{faces.max()}")
    return faces.astype(np.int64)
