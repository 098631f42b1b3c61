"""Correspondence: vertex ids, JSON files, snapping points to the surface, and the automatic route
(render the character, track the render with MediaPipe) checked against a head whose landmarks
are known by construction."""

import json

import numpy as np
import pytest

from keyshape.exceptions import InputError, RigError
from keyshape.mesh import mesh_components, snap_to_surface, weld_vertices
from keyshape.targets import Correspondence, find_correspondence, read_correspondence


def grid(side=6, size=1.0):
    """A flat square mesh in z = 0: vertices (side², 3) and faces."""
    u, v = np.meshgrid(np.linspace(0, size, side), np.linspace(0, size, side))
    vertices = np.stack([u.ravel(), v.ravel(), np.zeros(side * side)], axis=1)
    i, j = np.meshgrid(np.arange(side - 1), np.arange(side - 1), indexing="ij")
    a = (i * side + j).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + side], 1), np.stack([a + 1, a + side + 1, a + side], 1)])
    return vertices, faces


def test_vertex_ids_points_and_matrix():
    vertices, _ = grid()
    corr = Correspondence.from_vertex_ids([3, 7, 11], n_landmarks=5)
    assert corr.n_corr == 3 and corr.landmarks.tolist() == [0, 1, 2]
    np.testing.assert_array_equal(corr.points(vertices), vertices[[3, 7, 11]])
    np.testing.assert_allclose(corr.matrix(len(vertices)) @ vertices, corr.points(vertices))
    deltas = np.random.default_rng(0).normal(size=(4, len(vertices), 3))
    assert corr.points(deltas).shape == (4, 3, 3)  # works on stacks of targets too


@pytest.mark.parametrize("kwargs, message", [
    ({"landmarks": [0, 0], "vertices": [[1] * 3] * 2, "weights": [[1, 0, 0]] * 2}, "repeated landmarks"),
    ({"landmarks": [9], "vertices": [[1] * 3], "weights": [[1, 0, 0]]}, r"landmark indices must be in 0\.\.4"),
    ({"landmarks": [0], "vertices": [[1] * 3], "weights": [[0.5, 0, 0]]}, "summing to 1"),
    ({"landmarks": [0, 1], "vertices": [[1] * 3], "weights": [[1, 0, 0]]}, "as many landmarks"),
])
def test_correspondence_validation(kwargs, message):
    with pytest.raises(InputError, match=message):
        Correspondence(n_landmarks=5, **kwargs)


def test_check_names_the_mismatch():
    corr = Correspondence.from_vertex_ids({0: 40}, n_landmarks=68)
    with pytest.raises(RigError, match="uses vertex 40 but the mesh has 36 vertices"):
        corr.check(36)
    with pytest.raises(RigError, match="for 68 landmarks but the key shapes have 478"):
        corr.check(100, 478)


def test_snap_to_surface_finds_the_closest_point():
    vertices, faces = grid(side=5, size=4.0)
    points = np.array([[1.3, 2.6, 0.7], [-1.0, -1.0, 0.0], [2.0, 5.0, -0.2]])
    triangles, weights = snap_to_surface(points, vertices, faces)
    snapped = np.einsum("ij,ijd->id", weights, vertices[triangles])
    np.testing.assert_allclose(snapped, [[1.3, 2.6, 0.0], [0.0, 0.0, 0.0], [2.0, 4.0, 0.0]], atol=1e-12)
    assert (weights >= 0).all() and np.allclose(weights.sum(axis=1), 1)


def test_snap_matches_brute_force_on_a_curved_surface():
    rng = np.random.default_rng(3)
    vertices, faces = grid(side=12, size=1.0)
    vertices[:, 2] = 0.3 * np.sin(3 * vertices[:, 0]) * np.cos(2 * vertices[:, 1])
    points = rng.uniform([0, 0, -0.4], [1, 1, 0.4], (20, 3))
    triangles, weights = snap_to_surface(points, vertices, faces)
    found = np.linalg.norm(np.einsum("ij,ijd->id", weights, vertices[triangles]) - points, axis=1)
    dense = np.stack([rng.dirichlet(np.ones(3), 400) for _ in range(len(faces))])  # samples on every face
    samples = np.einsum("fsj,fjd->fsd", dense, vertices[faces]).reshape(-1, 3)
    brute = np.linalg.norm(samples[None] - points[:, None], axis=2).min(axis=1)
    assert (found <= brute + 1e-9).all()


def test_json_forms_round_trip(tmp_path):
    vertices, faces = grid()
    data = {"format": "keyshape-correspondence", "version": 1, "n_landmarks": 478,
            "landmarks": {"33": 4, "263": [0.5, 0.5, 0.2],
                          "61": {"vertices": [0, 1, 6], "weights": [2, 1, 1]}}}
    path = tmp_path / "corr.json"
    path.write_text(json.dumps(data))
    corr = read_correspondence(path, vertices, faces)
    assert corr.n_landmarks == 478 and corr.landmarks.tolist() == [33, 263, 61]
    np.testing.assert_allclose(corr.points(vertices)[1], [0.5, 0.5, 0.0], atol=1e-12)  # snapped
    np.testing.assert_allclose(corr.weights[2], [0.5, 0.25, 0.25])  # normalised
    again = read_correspondence(corr.save(tmp_path / "again.json"), vertices, faces)
    np.testing.assert_allclose(again.points(vertices), corr.points(vertices), atol=1e-6)
    assert again.n_landmarks == 478


def test_bare_forms(tmp_path):
    vertices, faces = grid()
    (tmp_path / "list.json").write_text("[5, 6, 7]")
    assert read_correspondence(tmp_path / "list.json", vertices, faces).landmarks.tolist() == [0, 1, 2]
    (tmp_path / "object.json").write_text('{"10": 5, "12": 6}')
    corr = read_correspondence(tmp_path / "object.json", vertices, faces, n_landmarks=68)
    assert corr.n_landmarks == 68 and corr.vertices[:, 0].tolist() == [5, 6]


@pytest.mark.parametrize("content, error, message", [
    ('{"3": 99}', RigError, "landmark 3: vertex 99 is not in the mesh"),
    ('{"x": 1}', InputError, "landmark keys must be integers"),
    ('{"3": "nose"}', InputError, "landmark 3: expected a vertex id"),
    ('{"3": {"vertices": [1, 2]}}', InputError, "landmark 3: a barycentric point needs"),
    ('{"3": true}', InputError, "landmark 3: expected a vertex id"),
    ("{}", InputError, "names no landmarks"),
    ("not json", InputError, "not a readable JSON file"),
])
def test_bad_files_name_the_problem(tmp_path, content, error, message):
    vertices, faces = grid()
    path = tmp_path / "bad.json"
    path.write_text(content)
    with pytest.raises(error, match=message):
        read_correspondence(path, vertices, faces)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="correspondence file not found"):
        read_correspondence(tmp_path / "nope.json", *grid())


def test_welding_joins_split_seams():
    vertices, faces = grid(side=3)
    # split the mesh along a seam: the right column of faces uses duplicated vertices
    extra = vertices[[1, 4, 7]]
    split = faces.copy()
    right = (vertices[faces][:, :, 0] > 0.4).all(axis=1)
    remap = {1: 9, 4: 10, 7: 11}
    split[right] = np.vectorize(lambda v: remap.get(v, v))(faces[right])
    seamed = np.vstack([vertices, extra])
    index, n = weld_vertices(seamed)
    assert n == 9 and index[9] == index[1]
    assert len(np.unique(mesh_components(seamed, split))) == 1


def test_components_are_numbered_by_size():
    vertices, faces = grid(side=4)
    small, small_faces = grid(side=2)
    both = np.vstack([vertices, small + [5, 0, 0]])
    label = mesh_components(both, np.vstack([faces, small_faces + len(vertices)]))
    assert (label[: len(vertices)] == 0).all() and (label[len(vertices):] == 1).all()


# ---------------------------------------------------------------- automatic, on a head with known landmarks


@pytest.fixture(scope="module")
def head():
    from keyshape.targets import stylised_head

    return stylised_head()


def test_found_landmarks_sit_where_the_head_was_built(head):
    """The stylised head's vertex i is MediaPipe landmark i by construction: rendering it and tracking
    the render must find each landmark near that vertex."""
    rig = head.rig
    corr = find_correspondence(rig.vertices, rig.faces)
    assert corr.n_landmarks == 478 and corr.n_corr > 430  # a few ambiguous ones are dropped
    face = corr.landmarks < 468
    found = corr.points(rig.vertices)[face]
    built = rig.vertices[head.landmark_vertices][corr.landmarks[face]]
    distance = np.linalg.norm(found - built, axis=1)
    eye_distance = np.linalg.norm(rig.vertices[33] - rig.vertices[263])
    assert np.median(distance) < 0.06 * eye_distance, np.median(distance) / eye_distance
    assert np.percentile(distance, 90) < 0.15 * eye_distance
    eyes = np.concatenate(head.rigid)
    assert not np.isin(corr.vertices, eyes).any()  # never on an eyeball
    quality = corr.quality()  # measured: median 0 %, 95 % within 1.1 % of the render's width, 32 moved
    assert quality["landmarks_kept"] == corr.n_corr and quality["median_residual_pct"] < 0.5
    assert 0 < quality["p95_residual_pct"] < 3 and 0 < quality["moved"] < 60


def test_the_front_is_found_on_a_z_up_head(head):
    """A Z-up export facing -Y (Blender's front view): found by the views tried, the same landmarks."""
    from keyshape.targets._correspond_auto import view_rotation

    rig = head.rig
    to_z_up = view_rotation("-y", "+z").T  # glTF's +Z front -> -Y, +Y up -> +Z
    z_up = rig.vertices @ to_z_up.T
    np.testing.assert_allclose(z_up[:, 2].max() - z_up[:, 2].min(), np.ptp(rig.vertices[:, 1]))
    corr = find_correspondence(z_up, rig.faces)
    plain = find_correspondence(rig.vertices, rig.faces)
    shared = np.intersect1d(corr.landmarks, plain.landmarks)
    assert len(shared) > 0.95 * plain.n_corr
    moved = corr.points(z_up)[np.searchsorted(corr.landmarks, shared)]
    there = plain.points(rig.vertices)[np.searchsorted(plain.landmarks, shared)] @ to_z_up.T
    eye_distance = np.linalg.norm(rig.vertices[33] - rig.vertices[263])
    assert np.percentile(np.linalg.norm(moved - there, axis=1), 95) < 0.02 * eye_distance
    with pytest.raises(RigError, match=r"facing \+Z tried.*--front AXIS"):
        find_correspondence(z_up, rig.faces, front="+z")
    with pytest.raises(InputError, match="front must be one of"):
        find_correspondence(z_up, rig.faces, front="up")


def test_no_face_on_the_render_is_a_clear_error():
    u, v = np.meshgrid(np.linspace(0, np.pi, 20), np.linspace(0, 2 * np.pi, 40))
    sphere = np.stack([np.sin(u) * np.cos(v), np.sin(u) * np.sin(v), np.cos(u)], axis=-1).reshape(-1, 3) * 0.1
    from scipy.spatial import ConvexHull

    faces = ConvexHull(sphere).simplices
    with pytest.raises(RigError, match="MediaPipe found no face on a front render"):
        find_correspondence(sphere, faces, size=256)


def test_see_through_parts_are_left_out_of_the_render(head):
    """A transparent visor in front of the face (alpha 0, as an eye overlay or a lash card): not drawn."""
    rig = head.rig
    lo, hi = rig.vertices.min(axis=0), rig.vertices.max(axis=0)
    front = hi[2] + 0.01
    visor = np.array([[lo[0], lo[1], front], [hi[0], lo[1], front], [hi[0], hi[1], front], [lo[0], hi[1], front]])
    n = rig.n_vertices
    vertices = np.vstack([rig.vertices, visor])
    faces = np.vstack([rig.faces, [[n, n + 1, n + 2], [n, n + 2, n + 3]]])
    rgba = np.hstack([np.full((len(vertices), 3), 0.8), np.ones((len(vertices), 1))])
    rgba[n:, 3] = 0.0
    corr = find_correspondence(vertices, faces, colours=rgba)
    assert corr.n_corr > 430 and corr.vertices.max() < n  # never on the visor
    with pytest.raises(RigError, match="found no face"):
        find_correspondence(vertices, faces, front="+z")  # drawn opaque, the visor hides the face
