"""Expression transfer: key motion into the character's space and proportions, spread over the mesh
(biharmonic, geodesic falloff), other regions held, rigid parts rigid or still."""

import numpy as np
import pytest

from keyshape.containers import KeyShapes
from keyshape.exceptions import RigError
from keyshape.schemes import resolve_regions
from keyshape.targets import Correspondence, feature_groups, landmark_motion, transfer_expressions

PX = 2000.0  # pixels per metre of the synthetic actor


def to_image(points):
    """glTF metres -> image pixels (x right, y down, z away), as a tracker would report them."""
    points = np.asarray(points, dtype=float)
    return np.stack([320 + PX * points[..., 0], 240 - PX * points[..., 1], -PX * points[..., 2]], axis=-1)


def sheet(side=25, size=0.2):
    """A curved face-sized sheet facing +Z: vertices (side², 3), faces."""
    u, v = np.meshgrid(np.linspace(-1, 1, side), np.linspace(-1, 1, side))
    vertices = np.stack([size / 2 * u.ravel(), size / 2 * v.ravel(), 0.03 * (1 - 0.5 * u.ravel() ** 2)], axis=1)
    i, j = np.meshgrid(np.arange(side - 1), np.arange(side - 1), indexing="ij")
    a = (i * side + j).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + side], 1), np.stack([a + 1, a + side + 1, a + side], 1)])
    return vertices, faces


def sheet_keys(vertices, landmark_vertices, deltas, *, regions=None, dims=3):
    """Key shapes whose landmarks are the sheet's ``landmark_vertices`` seen by the actor's camera."""
    n = len(landmark_vertices)
    regions = regions or {"whole": np.arange(n)}
    neutral = to_image(vertices[landmark_vertices])[:, :dims]
    moved = to_image(vertices[landmark_vertices][None] + deltas)[..., :dims]
    names = tuple(f"k{i}" for i in range(len(deltas)))
    return KeyShapes(neutral, moved - neutral, names, np.arange(len(deltas)), ("whole",) * len(deltas), regions,
                     stable=np.zeros(0, dtype=int))


@pytest.fixture(scope="module")
def head():
    from keyshape.targets import stylised_head

    return stylised_head()


def head_keys(head, moves: dict, *, region="lower", dims=3):
    """MediaPipe key shapes of an actor shaped like the head: one key per entry of ``moves``
    (landmark -> glTF displacement in metres)."""
    neutral = head.rig.vertices[head.landmark_vertices]
    eyes = [neutral[[33, 133]].mean(axis=0), neutral[[362, 263]].mean(axis=0)]
    neutral = np.vstack([neutral, np.repeat(eyes, 5, axis=0)])  # 478: irises at the eye centres
    deltas = np.zeros((len(moves), 478, 3))
    for k, move in enumerate(moves.values()):
        for landmark, shift in move.items():
            deltas[k, landmark] = shift
    image = to_image(neutral)[:, :dims]
    image_deltas = (to_image(neutral[None] + deltas) - to_image(neutral)[None])[..., :dims]
    regions = resolve_regions("upper-lower", 478)
    return KeyShapes(image, image_deltas, tuple(moves), np.arange(len(moves)), (region,) * len(moves), regions)


# ---------------------------------------------------------------- into the character's space


@pytest.mark.parametrize("dims", [3, 2])
def test_motion_undoes_the_camera(dims):
    vertices, faces = sheet()
    rng = np.random.default_rng(0)
    landmarks = rng.choice(len(vertices), 30, replace=False)
    truth = rng.normal(scale=0.004, size=(3, 30, 3))
    keys = sheet_keys(vertices, landmarks, truth, dims=dims)
    corr = Correspondence.from_vertex_ids(landmarks)
    motion = landmark_motion(keys, corr, vertices, faces, rescale=False)
    assert motion.scale == pytest.approx(1 / PX)
    expected = truth.copy()
    if dims == 2:
        expected[..., 2] = 0  # a 2D track says nothing about depth
    np.testing.assert_allclose(motion.deltas, expected, atol=1e-9)
    assert motion.n_dims == dims and motion.constrained.all()


def test_motion_follows_a_turned_character():
    """3D key shapes are turned onto a character in any orientation (a similarity, Umeyama)."""
    from scipy.spatial.transform import Rotation

    vertices, faces = sheet()
    rng = np.random.default_rng(1)
    landmarks = rng.choice(len(vertices), 40, replace=False)
    truth = rng.normal(scale=0.004, size=(2, 40, 3))
    keys = sheet_keys(vertices, landmarks, truth)
    turn = Rotation.from_euler("xyz", [90, 20, -30], degrees=True).as_matrix()
    turned = 3.0 * vertices @ turn.T + [1.0, 2.0, 3.0]  # bigger, turned and moved
    motion = landmark_motion(keys, Correspondence.from_vertex_ids(landmarks), turned, faces, rescale=False)
    np.testing.assert_allclose(motion.deltas, 3.0 * truth @ turn.T, atol=1e-9)


def test_features_are_rescaled_to_the_character(head):
    """A character with eyes twice as tall gets twice the vertical eye motion (its lids still meet)."""
    rig = head.rig
    keys = head_keys(head, {"blink": {159: [0, -0.004, 0], 145: [0, 0.001, 0]}}, region="upper")
    corr = head.correspondence()
    plain = landmark_motion(keys, corr, rig.vertices, rig.faces)
    right_eye = feature_groups(478)["right_eye"]
    tall = np.array(rig.vertices)
    centre = tall[right_eye].mean(axis=0)
    tall[right_eye, 1] = centre[1] + 2 * (tall[right_eye, 1] - centre[1])
    stretched = landmark_motion(keys, corr, tall, rig.faces)
    assert stretched.feature_scales["right_eye"][1] == pytest.approx(2 * plain.feature_scales["right_eye"][1], rel=0.05)
    assert stretched.deltas[0, 159, 1] == pytest.approx(2 * plain.deltas[0, 159, 1], rel=0.05)
    assert plain.deltas[0, 159, 1] == pytest.approx(-0.004, rel=0.05)  # the actor is shaped like the head


def test_silhouette_landmarks_are_trusted_less(head):
    keys = head_keys(head, {"k": {152: [0, -0.005, 0]}})
    motion = landmark_motion(keys, head.correspondence(), head.rig.vertices, head.rig.faces)
    assert motion.confidence[1] == 1.0  # nose tip faces the camera
    assert motion.confidence[234] < 0.5  # the face outline beside the ear is edge-on


def test_too_few_or_degenerate_correspondences():
    vertices, _ = sheet()
    keys = sheet_keys(vertices, np.arange(5), np.zeros((1, 5, 3)))
    with pytest.raises(RigError, match="at least 3 corresponded landmarks"):
        landmark_motion(keys, Correspondence.from_vertex_ids({0: 0, 1: 1}, n_landmarks=5), vertices)
    with pytest.raises(RigError, match="degenerate"):
        landmark_motion(keys, Correspondence.from_vertex_ids({0: 0, 1: 0, 2: 0}, n_landmarks=5), vertices)


# ---------------------------------------------------------------- over the mesh


def test_spread_reproduces_the_landmarks_and_fades_out():
    vertices, faces = sheet(side=41)
    side = 41
    centre = 20 * side + 20
    ring = [centre - 3, centre + 3, centre - 3 * side, centre + 3 * side]
    landmarks = np.array([centre, *ring])
    truth = np.zeros((1, 5, 3))
    truth[0, 0] = [0.0, 0.0, 0.004]  # push the middle out; its ring holds
    keys = sheet_keys(vertices, landmarks, truth)
    field = transfer_expressions(keys, vertices, faces, Correspondence.from_vertex_ids(landmarks), falloff=0.6)
    np.testing.assert_allclose(field[0, landmarks], truth[0], atol=2e-4)
    corners = [0, side - 1, side * (side - 1), side * side - 1]
    assert np.abs(field[0, corners]).max() == 0.0  # beyond the falloff: held still
    neighbour = field[0, centre + 1, 2]
    assert 0 < neighbour < 0.004  # smooth in between


def test_field_is_linear_in_the_key_motion(head):
    a = {183: [0, -0.003, 0.001], 14: [0, -0.004, 0]}
    b = {61: [-0.003, 0.002, 0], 291: [0.003, 0.002, 0]}
    keys = head_keys(head, {"a": a, "b": b, "ab": {}})
    deltas = np.array(keys.deltas)
    deltas[2] = deltas[0] + deltas[1]
    keys = KeyShapes(keys.neutral, deltas, keys.names, keys.frames, keys.key_regions, keys.regions)
    field = transfer_expressions(keys, head.rig.vertices, head.rig.faces, head.correspondence())
    np.testing.assert_allclose(field[2], field[0] + field[1], atol=1e-9)


def test_a_mouth_key_moves_the_mouth_only(head):
    rig = head.rig
    jaw = {i: [0, -0.008, -0.002] for i in (14, 87, 178, 88, 95, 317, 402, 318, 324, 17, 84, 314, 152, 148, 377)}
    keys = head_keys(head, {"open": jaw})
    field = transfer_expressions(keys, rig.vertices, rig.faces, head.correspondence())
    lower_lip, upper_lip = 14, 13
    assert field[0, lower_lip, 1] < -0.006  # the lower lip drops
    assert abs(field[0, upper_lip, 1]) < 0.0015  # the upper lip, across the mouth opening, barely moves
    upper = resolve_regions("upper-lower", 478)["upper"]
    assert np.abs(field[0, upper]).max() < 1e-4  # the other region's landmarks are held
    back = rig.vertices[:, 2] < -0.1
    assert np.abs(field[0, back]).max() == 0.0  # the back of the head stays
    eyes = np.concatenate(head.rigid)
    assert np.abs(field[0, eyes]).max() == 0.0  # eyeballs (separate parts) stay still


def test_separate_parts_stay_still_and_listed_parts_move_rigidly():
    vertices, faces = sheet(side=31)
    side = 31
    middle = 15 * side + 15
    landmarks = np.array([middle, middle - 6, middle + 6, middle - 6 * side, middle + 6 * side])
    truth = np.zeros((1, 5, 3))
    truth[0, 0] = [0.002, 0.0, 0.003]
    loose = vertices[[0, 1, side]] + [0.0, 0.0, 0.05]  # a separate triangle above the sheet
    mesh = np.vstack([vertices, loose])
    tri = np.vstack([faces, [[len(vertices), len(vertices) + 1, len(vertices) + 2]]])
    keys = sheet_keys(mesh, landmarks, truth)
    corr = Correspondence.from_vertex_ids(landmarks)
    still = transfer_expressions(keys, mesh, tri, corr)
    assert np.abs(still[0, len(vertices):]).max() == 0.0
    patch = np.array([middle + k for k in (-1, 0, 1, -side, side, side + 1)])
    moved = transfer_expressions(keys, mesh, tri, corr, rigid=[patch])
    before = mesh[patch]
    after = before + moved[0, patch]

    def pairwise(p):
        return np.linalg.norm(p[:, None] - p[None], axis=2)

    np.testing.assert_allclose(pairwise(after), pairwise(before), atol=1e-12)
    assert np.linalg.norm(moved[0, patch].mean(axis=0)) > 0.001  # and it moved with the skin


def test_seams_do_not_tear():
    """A glTF-style seam (duplicated vertices) moves as one surface."""
    vertices, faces = sheet(side=21)
    side = 21
    seam = np.flatnonzero(np.isclose(vertices[:, 0], 0.0))
    copies = np.arange(len(vertices), len(vertices) + len(seam))
    right = (vertices[faces][:, :, 0] > -1e-9).all(axis=1)
    remap = dict(zip(seam, copies))
    split = faces.copy()
    split[right] = np.vectorize(lambda v: remap.get(v, v))(faces[right])
    mesh = np.vstack([vertices, vertices[seam]])
    middle = 10 * side + 10
    landmarks = np.array([middle - 2, middle + 2 * side, middle - 2 * side])
    keys = sheet_keys(mesh, landmarks, np.full((1, 3, 3), 0.002))
    field = transfer_expressions(keys, mesh, split, Correspondence.from_vertex_ids(landmarks))
    np.testing.assert_allclose(field[0, copies], field[0, seam], atol=1e-12)
