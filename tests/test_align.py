"""Alignment: Umeyama similarity recovery, no reflections, NaN frames, poses of a synthetic take."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from keyshape.alignment import align, choose_neutral, procrustes
from keyshape.containers import Track
from keyshape.datasets import make_performance
from keyshape.exceptions import DegenerateFrameWarning, InputError, KeyshapeError


def _rotation(d, angles):
    """A proper rotation from 1 (2D) or 3 (3D) angles, radians."""
    a, b, c = angles
    if d == 2:
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rx = np.array([[1, 0, 0], [0, np.cos(c), -np.sin(c)], [0, np.sin(c), np.cos(c)]])
    return rz @ ry @ rx


angle = st.floats(-np.pi, np.pi)


@settings(max_examples=60, deadline=None)
@given(
    d=st.sampled_from([2, 3]),
    angles=st.tuples(angle, angle, angle),
    scale=st.floats(0.1, 10.0),
    shift=st.tuples(*[st.floats(-500, 500)] * 3),
    seed=st.integers(0, 2**16),
)
def test_procrustes_recovers_known_similarity(d, angles, scale, shift, seed):
    source = np.random.default_rng(seed).normal(size=(10, d)) * 50
    rotation, translation = _rotation(d, angles), np.array(shift[:d])
    target = scale * source @ rotation.T + translation
    poses = procrustes(source, target)
    np.testing.assert_allclose(poses.rotations[0], rotation, atol=1e-8)
    np.testing.assert_allclose(poses.scales[0], scale, rtol=1e-8)
    np.testing.assert_allclose(poses.translations[0], translation, atol=1e-6 * (1 + scale * 50))
    np.testing.assert_allclose(poses.to_image(source[None])[0], target, atol=1e-6 * (1 + scale * 50))


@pytest.mark.parametrize("d", [2, 3])
def test_procrustes_never_reflects(d):
    rng = np.random.default_rng(1)
    source = rng.normal(size=(8, d))
    mirrored = source * np.r_[-1.0, np.ones(d - 1)]  # a reflection fits exactly, a rotation cannot
    poses = procrustes(source, mirrored)
    np.testing.assert_allclose(np.linalg.det(poses.rotations[0]), 1.0)
    np.testing.assert_allclose(poses.rotations[0] @ poses.rotations[0].T, np.eye(d), atol=1e-12)


def test_procrustes_without_scale_keeps_unit_scale():
    source = np.random.default_rng(2).normal(size=(6, 3))
    poses = procrustes(source, 3.0 * source, scale=False)
    assert poses.scales[0] == 1.0
    np.testing.assert_allclose(poses.rotations[0], np.eye(3), atol=1e-12)


def test_procrustes_batched_matches_single_frames_and_keeps_nan():
    rng = np.random.default_rng(3)
    source = rng.normal(size=(7, 3))
    targets = rng.normal(size=(5, 7, 3))
    targets[2] = np.nan
    batch = procrustes(source, targets)
    assert np.isnan(batch.rotations[2]).all() and np.isnan(batch.scales[2])
    for f in (0, 1, 3, 4):
        single = procrustes(source, targets[f])
        np.testing.assert_allclose(batch.rotations[f], single.rotations[0], atol=1e-12)
        np.testing.assert_allclose(batch.translations[f], single.translations[0], atol=1e-12)


def test_rotations_by_newton_are_the_svd_rotations():
    """3D frames solved by Newton's polar iteration give Umeyama's U S Vᵀ of the SVD to rounding;
    a reflection (det Σ < 0), rank-deficient and ill-conditioned frames take the SVD itself."""
    from keyshape.alignment._procrustes import _polar, _rotations

    rng = np.random.default_rng(3)
    cov = rng.standard_normal((400, 3, 3)) * 10.0 ** rng.uniform(-3, 3, (400, 1, 1))
    cov *= np.sign(np.linalg.det(cov))[:, None, None]  # det Σ > 0, as a face's stable points give
    cov[:4] = [np.diag([1.0, 1.0, -1.0]), np.outer([1.0, 2, 3], [3.0, 1, 2]), np.diag([1.0, 1.0, 1e-8]),
               np.diag([1.0, 1e-9, 1e-9])]
    rotations, trace, good = _rotations(cov)
    u, sv, vt = np.linalg.svd(cov)
    sign = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    expected = (u * np.stack([np.ones_like(sign), np.ones_like(sign), sign], axis=1)[:, None, :]) @ vt
    np.testing.assert_allclose(rotations, expected, atol=1e-12)
    np.testing.assert_allclose(trace, sv[:, :2].sum(axis=1) + sign * sv[:, 2], rtol=1e-12)
    assert good.tolist()[:4] == [True, False, True, True]
    newton = ~_polar(cov)[1]
    assert not newton[:4].any() and newton[4:].mean() > 0.9  # most random frames are well posed


def test_procrustes_degenerate_frame_warns_and_is_nan():
    source = np.random.default_rng(4).normal(size=(5, 3))
    targets = np.stack([source, np.zeros((5, 3))])
    with pytest.warns(DegenerateFrameWarning, match="1 frame"):
        poses = procrustes(source, targets)  # frame 1 collapses to one point
    np.testing.assert_allclose(poses.scales[0], 1.0)
    assert np.isnan(poses.scales[1]) and np.isnan(poses.rotations[1]).all()


def test_procrustes_rejects_bad_shapes():
    with pytest.raises(InputError, match="source must have shape"):
        procrustes(np.zeros((4, 4)), np.zeros((4, 4)))
    with pytest.raises(InputError, match="same points"):
        procrustes(np.zeros((4, 3)), np.zeros((5, 3)))


@pytest.mark.parametrize("n_dims", [2, 3])
def test_align_exact_without_noise(n_dims):
    perf = make_performance(n_frames=40, n_dims=n_dims, noise=0.0, n_missing=3)
    aligned, poses = align(perf.track, reference=perf.neutral, stable=perf.stable)
    valid = perf.track.valid
    np.testing.assert_allclose(poses.rotations[valid], perf.true_poses.rotations[valid], atol=1e-9)
    np.testing.assert_allclose(poses.scales[valid], perf.true_poses.scales[valid], rtol=1e-9)
    np.testing.assert_allclose(aligned.points[valid], perf.canonical[valid], atol=1e-7)
    assert np.isnan(aligned.points[~valid]).all() and np.isnan(poses.rotations[~valid]).all()


@pytest.mark.parametrize("n_dims", [2, 3])
def test_align_recovers_true_poses_under_pixel_noise(n_dims):
    perf = make_performance(n_frames=200, n_dims=n_dims, noise=0.5, n_missing=5)
    aligned, poses = align(perf.track, reference=perf.neutral, stable=perf.stable)
    valid = perf.track.valid
    # Rotation error angle from the trace of R_est R_trueᵀ.
    rel = np.einsum("fij,fkj->fik", poses.rotations[valid], perf.true_poses.rotations[valid])
    angle = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - (n_dims - 2)) / 2, -1, 1))
    # 0.5 px noise on 8 stable points ~35 px from their centre: ~0.3° per axis expected.
    assert np.degrees(angle).mean() < 1.0 and np.degrees(angle).max() < 3.0
    assert np.abs(poses.scales[valid] / perf.true_poses.scales[valid] - 1).max() < 0.03
    assert np.abs(poses.translations[valid] - perf.true_poses.translations[valid]).max() < 3.0
    # The aligned landmarks sit near the noiseless expression (noise is √d · 0.5 px per point).
    rms = np.sqrt(((aligned.points[valid] - perf.canonical[valid]) ** 2).sum(axis=2).mean())
    assert rms < 1.5 * 0.5 * np.sqrt(n_dims)


def test_align_keeps_metadata_and_accepts_a_reference_frame():
    perf = make_performance(n_frames=30, n_dims=2)
    aligned, poses = align(perf.track, reference=4, stable=perf.stable, scale=False)
    assert aligned.fps == perf.track.fps and aligned.image_size == perf.track.image_size
    assert poses.n_frames == 30 and np.all(poses.scales == 1.0)
    np.testing.assert_allclose(aligned.points[4], perf.track.points[4], atol=1e-9)


def test_align_rejects_bad_reference_and_stable():
    perf = make_performance(n_frames=20)
    with pytest.raises(InputError, match="reference must have shape"):
        align(perf.track, reference=np.zeros((3, 3)), stable=perf.stable)
    with pytest.raises(InputError, match="stable indices must lie in"):
        align(perf.track, reference=perf.neutral, stable=np.array([0, 1, 99]))


def test_choose_neutral_returns_a_resting_valid_frame():
    perf = make_performance(n_frames=200, n_missing=10)
    frame = choose_neutral(perf.track, stable=perf.stable, regions=perf.regions)
    assert perf.track.valid[frame]
    assert perf.true_weights[frame].sum() < 0.1  # a resting frame: (almost) no key active


def test_choose_neutral_without_faces_raises():
    track = Track(np.full((5, 20, 3), np.nan), fps=30)
    with pytest.raises(KeyshapeError, match="no frame with a face"):
        choose_neutral(track, stable=np.arange(5))
