"""Eye gaze from the irises: yaw and pitch per eye, as separate channels (never blended).

Each iris centre is measured against its eye's corners in head-aligned coordinates: the
offset along the corner-to-corner axis gives yaw, across it pitch. The iris rides on a
sphere of radius ``r = EYEBALL_RATIO · eye width`` (an eyeball of about 12 mm for a
palpebral fissure of about 29 mm), so an offset ``d`` is an angle ``arcsin(d / r)``.
Angles are relative to the neutral frame, where the actor is assumed to look ahead.

Conventions: yaw > 0 when the eye turns toward the actor's left (image +x for a frontal face),
pitch > 0 when it looks up. Degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..exceptions import InputError
from ..schemes import mediapipe_scheme

__all__ = ["Gaze", "estimate_gaze", "EYEBALL_RATIO"]

EYEBALL_RATIO = 0.42
# (outer corner, inner corner) of the actor's right and left eye in MediaPipe's mesh
_CORNERS = {"right": (33, 133), "left": (263, 362)}


@dataclass(frozen=True)
class Gaze:
    """Per-eye gaze angles in degrees.

    yaw, pitch : (n_frames, 2) float, columns (right eye, left eye); NaN where no face
    """

    yaw: np.ndarray
    pitch: np.ndarray

    n_frames = property(lambda self: self.yaw.shape[0])

    def rotations(self) -> np.ndarray:
        """Eye rotations ``(n_frames, 2, 3, 3)`` relative to the head, LEFT eye first.

        Image convention (x right, y down, z away from the camera), as the exporters take them:
        ``R = R_y(−yaw) · R_x(−pitch)`` turns the rest direction (toward the camera, −z) into the
        gaze direction ``(sin yaw · cos pitch, −sin pitch, −cos yaw · cos pitch)``. NaN angles
        (no face) give the identity.
        """
        yaw = np.radians(np.nan_to_num(self.yaw[:, ::-1]))  # (right, left) -> (left, right)
        pitch = np.radians(np.nan_to_num(self.pitch[:, ::-1]))
        return np.einsum("feij,fejk->feik", _about_y(-yaw), _about_x(-pitch))


def _about_y(angle: np.ndarray) -> np.ndarray:
    c, s, z, o = np.cos(angle), np.sin(angle), np.zeros_like(angle), np.ones_like(angle)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _about_x(angle: np.ndarray) -> np.ndarray:
    c, s, z, o = np.cos(angle), np.sin(angle), np.zeros_like(angle), np.ones_like(angle)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _iris_ids(eye: str) -> np.ndarray:
    return np.array(mediapipe_scheme()["contours"][f"{eye}_iris"])


def _eye_offsets(points: np.ndarray, eye: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Iris offset along (u) and across (v, image down) the eye axis, and the eye width."""
    outer, inner = (points[:, i, :2] for i in _CORNERS[eye])
    axis = inner - outer if eye == "right" else outer - inner  # points toward image +x
    width = np.linalg.norm(axis, axis=1)
    u = axis / width[:, None]
    v = np.stack([-u[:, 1], u[:, 0]], axis=1)  # u rotated +90° in image axes: points down
    d = points[:, _iris_ids(eye), :2].mean(axis=1) - (outer + inner) / 2
    return np.einsum("fi,fi->f", d, u), np.einsum("fi,fi->f", d, v), width


def estimate_gaze(points: np.ndarray, *, neutral_frame: int | None = None,
                  reference: np.ndarray | None = None) -> Gaze:
    """Yaw and pitch of each eye from MediaPipe's 478 landmarks.

    Parameters
    ----------
    points : (n_frames, 478, 2 or 3) float, head-aligned (see :func:`keyshape.alignment._procrustes.align`)
    neutral_frame : frame whose gaze is taken as straight ahead
    reference : (478, 2 or 3) float, a neutral shape whose gaze is straight ahead (e.g. the key
        set's neutral); with neither, offsets from the corner midpoint are used as they are

    Returns
    -------
    Gaze
    """
    points = np.asarray(points, dtype=float)
    if points.ndim != 3 or points.shape[1] != 478:
        raise InputError(f"gaze needs MediaPipe's 478 landmarks (with irises); got shape {points.shape}")
    if neutral_frame is not None:
        reference = points[neutral_frame]
    yaw, pitch = [], []
    for eye in ("right", "left"):
        du, dv, width = _eye_offsets(points, eye)
        if reference is not None:
            du0, dv0, _ = _eye_offsets(np.asarray(reference, dtype=float)[None], eye)
            du, dv = du - du0, dv - dv0
        radius = EYEBALL_RATIO * width
        yaw.append(np.degrees(np.arcsin(np.clip(du / radius, -1, 1))))
        pitch.append(np.degrees(np.arcsin(np.clip(-dv / radius, -1, 1))))
    return Gaze(np.stack(yaw, axis=1), np.stack(pitch, axis=1))
