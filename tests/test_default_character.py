"""The built-in stylised head as a user first sees it: eyes that follow the gaze, lids that close, a
mouth interior hidden at rest and shown with the jaw open, colours, and a head that turns in the
preview."""

from __future__ import annotations

import numpy as np
import pytest
from test_transfer import head_keys

from keyshape.containers import KeyShapes
from keyshape.render import make_renderer
from keyshape.render.camera import frame_points
from keyshape.render.raster import rasterize
from keyshape.targets import GAZE_NAMES, default_character, gaze_weights, stylised_head, with_gaze_targets

# upper lid -> lower lid landmarks of both eyes (MediaPipe)
LIDS = {246: 7, 161: 163, 160: 144, 159: 145, 158: 153, 157: 154, 173: 155,
        466: 249, 388: 390, 387: 373, 386: 374, 385: 380, 384: 381, 398: 382}
JAW = (14, 87, 178, 88, 95, 317, 402, 318, 324, 17, 84, 181, 91, 146, 314, 405, 321, 375, 152, 148, 176, 377,
       400, 199, 175, 200, 18)
INTERIOR = ("cavity", "upper_teeth", "lower_teeth", "tongue")


@pytest.fixture(scope="module")
def head():
    return stylised_head()


@pytest.fixture(scope="module")
def keys(head) -> KeyShapes:
    """A blink (upper lids onto the lower lids) and a jaw opening of 12 mm, on an actor shaped like the head."""
    points = head.rig.vertices[head.landmark_vertices]
    blink = {upper: points[lower] - points[upper] for upper, lower in LIDS.items()}
    jaw = {i: [0.0, -0.012, -0.002] for i in JAW}
    upper = head_keys(head, {"blink": blink}, region="upper")
    lower = head_keys(head, {"jaw": jaw}, region="lower")
    return KeyShapes(upper.neutral, np.concatenate([upper.deltas, lower.deltas]), ("blink", "jaw"), [0, 1],
                     ("upper", "lower"), upper.regions)


@pytest.fixture(scope="module")
def rig(keys):
    return with_gaze_targets(default_character(keys))


def _render(head, vertices, colours, size=400):
    camera = frame_points(head.rig.vertices, fov_deg=25.0, margin=1.12)
    with make_renderer(head.rig.faces, size, size, n_vertices=head.rig.n_vertices, colours=colours) as renderer:
        return renderer.render(vertices, camera)


def _pose(rig, **weights):
    values = np.zeros(rig.n_targets)
    for name, value in weights.items():
        values[rig.names.index(name)] = value
    return rig.pose(values[None])[0]


def test_irises_turn_with_the_gaze(head, rig):
    """eyeLookOut of the left eye (at +x) turns its pupil toward +x by the target's 30 degrees."""
    pupil = head.parts["left_eye"][0]  # the front pole: the pupil's centre
    centre = head.eye_centres[0]
    rest = rig.vertices[pupil] - centre
    turned = _pose(rig, eyeLookOutLeft=1.0)[pupil] - centre
    angle = np.degrees(np.arctan2(turned[0], turned[2]) - np.arctan2(rest[0], rest[2]))
    assert angle == pytest.approx(30.0, abs=1.0)
    up = _pose(rig, eyeLookUpRight=1.0)[head.parts["right_eye"][0]] - head.eye_centres[1]
    assert up[1] > rest[1] + 0.4 * np.linalg.norm(rest)  # looks up
    assert np.allclose(_pose(rig, eyeLookOutLeft=1.0)[head.parts["skin"]], rig.vertices[head.parts["skin"]])


def test_gaze_weights_follow_the_tracked_angles():
    # columns (right eye, left eye); yaw > 0 toward the character's +x (its left), pitch > 0 up
    weights = gaze_weights(np.array([[15.0, 15.0], [0.0, 0.0]]), np.array([[0.0, 0.0], [-30.0, np.nan]]))
    named = dict(zip(GAZE_NAMES, weights[0]))
    assert named["eyeLookOutLeft"] == pytest.approx(0.5) and named["eyeLookInRight"] == pytest.approx(0.5)
    assert named["eyeLookInLeft"] == 0 and named["eyeLookOutRight"] == 0
    assert dict(zip(GAZE_NAMES, weights[1]))["eyeLookDownRight"] == pytest.approx(1.0)
    assert weights[1].sum() == pytest.approx(1.0)  # NaN: no turn


def test_lids_close_on_a_blink_key(head, keys, rig):
    ids = head.landmark_vertices
    posed = _pose(rig, blink=1.0)
    upper, lower = ids[list(LIDS)], ids[list(LIDS.values())]
    open_gap = np.linalg.norm(rig.vertices[upper] - rig.vertices[lower], axis=1)
    closed_gap = np.linalg.norm(posed[upper] - posed[lower], axis=1)
    assert (closed_gap < 0.15 * open_gap).all(), closed_gap / open_gap
    # and the eyes are covered: the render shows (almost) no eyeball
    colours = np.tile([0.9, 0.7, 0.6], (rig.n_vertices, 1))
    colours[np.concatenate([head.parts["left_eye"], head.parts["right_eye"]])] = [0.0, 1.0, 0.0]
    shown = [_marked(_render(head, v, colours)) for v in (rig.vertices, posed)]
    assert shown[0] > 400 and shown[1] < 0.02 * shown[0], shown


def _marked(image: np.ndarray) -> int:
    """Pixels of the marker colour (pure green, shaded)."""
    r, g, b = (image[..., i].astype(int) for i in range(3))
    return int(((g > 60) & (g > 3 * r) & (g > 3 * b)).sum())


def test_the_mouth_interior_is_hidden_at_rest_and_shown_with_the_jaw_open(head, rig):
    colours = np.tile([0.9, 0.7, 0.6], (rig.n_vertices, 1))
    colours[np.concatenate([head.parts[p] for p in INTERIOR])] = [0.0, 1.0, 0.0]
    at_rest = _marked(_render(head, rig.vertices, colours))
    opened = _marked(_render(head, _pose(rig, jaw=1.0), colours))
    assert at_rest < 0.05 * opened and opened > 300, (at_rest, opened)  # at rest: the lip line only
    # the lower teeth and the tongue go down with the jaw, the upper teeth (with the upper lip) stay
    jaw = rig.deltas[rig.names.index("jaw")]
    assert jaw[head.parts["lower_teeth"], 1].mean() < -0.008
    assert np.abs(jaw[head.parts["upper_teeth"]]).max() < 0.001


LOWER_INNER_LIP = (78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308)  # corner to corner
UPPER_INNER_LIP = (78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308)
UPPER_LIP = (13, 82, 81, 80, 312, 311, 310, 0, 37, 39, 40, 267, 269, 270, 164, 191, 415, 185, 409)


def _parts_seen(head, vertices, size=400):
    """Which part each pixel of a front view of the mouth shows ``(size, size) int``: -1 the
    background, else the index into ``("skin", *INTERIOR)``; and the landmarks' pixel positions."""
    mouth = vertices[head.landmark_vertices[[61, 291, 0, 17]]]
    camera = frame_points(np.vstack([mouth, vertices[head.parts["skin"]][:, 2:] * [0, 0, 1]]), margin=1.6)
    screen, in_front = camera.to_screen(vertices, size, size)
    face = rasterize(screen, head.rig.faces, size, size, in_front=in_front)
    label = np.zeros(len(vertices), dtype=int)
    for i, name in enumerate(INTERIOR, 1):
        label[head.parts[name]] = i
    return np.where(face >= 0, label[head.rig.faces[np.maximum(face, 0), 0]], -1), screen[head.landmark_vertices]


@pytest.fixture(scope="module")
def mouth_keys(head):
    """The jaw opening of ``keys`` and a key like the demo's at frame 470: the whole mouth 8 mm up
    and 10 mm back (lips, jaw and the skin between; the actor's residual head motion)."""
    lower = (*JAW, *UPPER_LIP, 61, 291, 78, 308)
    shift = {i: [0.0, 0.008, -0.01] for i in lower}
    jaw = {i: [0.0, -0.012, -0.002] for i in JAW}
    return head_keys(head, {"jaw": jaw, "mouth_back": shift}, region="lower")


def test_the_teeth_stay_behind_the_lips_when_the_whole_mouth_moves(head, mouth_keys):
    """No tooth shows below the lower lip's inner edge (it would stand through the lip)."""
    rig = default_character(mouth_keys)
    for name in mouth_keys.names:
        seen, points = _parts_seen(head, rig.pose(np.eye(rig.n_targets)[[rig.names.index(name)]])[0])
        lip = points[list(LOWER_INNER_LIP)]
        rows, columns = np.nonzero((seen == 2) | (seen == 3))
        below = rows + 0.5 > np.interp(columns + 0.5, lip[:, 0], lip[:, 1]) + 1.0
        assert below.sum() == 0, (name, int(below.sum()), len(rows))


def test_the_head_is_coloured_and_symmetric(head):
    from keyshape.mesh import mirror_map

    colours = head.colours
    assert colours.shape == (head.rig.n_vertices, 3) and (colours >= 0).all() and (colours <= 1).all()
    assert len(np.unique(np.round(colours, 2), axis=0)) > 50  # skin, lips, brows, hair, eyes, teeth
    mirror, normal = mirror_map(head.rig.vertices)
    assert abs(normal[0]) > 0.99  # the plane x = 0
    reflected = head.rig.vertices[mirror] * [-1, 1, 1]
    assert np.median(np.linalg.norm(reflected - head.rig.vertices, axis=1)) < 1e-4  # (the skin within 3 mm)
    assert np.abs(colours[mirror] - colours).mean() < 0.01  # colours mirror too (lips' edge within a few vertices)


def test_the_head_turns_in_the_preview(rig):
    from scipy.spatial.transform import Rotation

    from keyshape.render.preview import _CharacterView

    weights = np.zeros((2, rig.n_targets))
    rotations = Rotation.from_euler("y", [[0.0], [35.0]], degrees=True).as_matrix()
    with _CharacterView(rig, weights, rotations, 200, "auto", stylised_head().colours) as view:
        still, turned = view(0), view(1)
    face = [np.argwhere((image[30:].astype(int) - image[-1, 0]).any(axis=2)) for image in (still, turned)]
    assert np.abs(still.astype(int) - turned.astype(int)).mean() > 5
    assert abs(face[1][:, 1].mean() - face[0][:, 1].mean()) > 3  # the head's picture moves as it turns


def test_the_lower_face_moves_at_the_actors_amplitude(head, keys, rig):
    """Landmark motion relative to face size (the RMS radius of the landmarks): the character's
    jaw key moves its landmarks as far as the actor's (the transfer alone gives about 0.8-0.9)."""
    ids = np.arange(468)
    actor, character = keys.neutral[ids, :2], rig.vertices[head.landmark_vertices[ids], :2]

    def radius(points):
        return np.sqrt(((points - points.mean(axis=0)) ** 2).sum(axis=1).mean())

    lower = np.asarray(keys.regions["lower"])
    lower = lower[lower < 468]
    a = np.linalg.norm(keys.deltas[1, lower, :2], axis=1) / radius(actor)
    jaw = rig.deltas[rig.names.index("jaw"), head.landmark_vertices[lower], :2]
    c = np.linalg.norm(jaw, axis=1) / radius(character)
    assert (c @ a) / (a @ a) == pytest.approx(1.0, abs=0.05)


def test_the_glb_carries_the_colours_and_passes_the_validator(head, rig, tmp_path):
    from keyshape.containers import Weights
    from keyshape.io.gltf import read_colours, write_glb

    from gltf_validator import validate

    weights = Weights(np.zeros((3, rig.n_targets)), rig.names, fps=24.0)
    path = write_glb(tmp_path / "head.glb", rig, weights, colours=head.colours)
    report = validate(path)
    assert (report["numErrors"], report["numWarnings"]) == (0, 0), report["messages"][:5]
    linear = read_colours(path)[:, :3]  # glTF's COLOR_0 is linear
    np.testing.assert_allclose(linear ** (1 / 2.4), head.colours, atol=0.06)
