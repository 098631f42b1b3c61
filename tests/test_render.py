"""Rendering: OpenGL and numpy agree, the rasteriser is right, the preview video is right."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import Delaunay

from keyshape.alignment import align
from keyshape.containers import Rig, Weights
from keyshape.datasets import make_performance
from keyshape.exceptions import InputError
from keyshape.keyshapes import find_keyshapes
from keyshape.render import RenderFallbackWarning, frame_points, make_renderer
from keyshape.render import _backend as render
from keyshape.render.camera import BACKGROUND
from keyshape.render.encode import VideoWriter, rate_of
from keyshape.render.raster import NumpyRenderer, rasterize

from conftest import write_video
from helpers import nonnegative_fit

BACKGROUND_RGB = np.round(BACKGROUND * 255)


# --------------------------------------------------------------------------- helpers shared with
# test_plots.py and test_report.py: a synthetic take folder as `keyshape run` writes it


def synthetic_take(*, n_frames: int = 48, n_missing: int = 3, rotation_deg: float = 0.0, seed: int = 0):
    """A synthetic performance (known neutral and extremes), its keys, NNLS weights and a rig."""
    perf = make_performance(n_frames=n_frames, n_landmarks=150, n_keys=4, noise=0.2, n_missing=n_missing,
                            rotation_deg=rotation_deg, delta_scale=10.0, fps=25.0, random_state=seed)
    aligned, poses = align(perf.track, reference=perf.neutral, stable=perf.stable)
    keys = find_keyshapes(aligned, regions=perf.regions, n_keys=2, neutral_frame=perf.neutral_frame,
                          stable=perf.stable)
    aligned, poses = align(perf.track, reference=keys.neutral, stable=perf.stable)
    values = np.full((n_frames, keys.n_keys), np.nan)
    ok = aligned.valid
    for region, lm in keys.regions.items():
        k = keys.keys_of(region)
        targets = (aligned.points[ok][:, lm] - keys.neutral[lm]).reshape(ok.sum(), -1)
        values[np.ix_(ok, k)] = nonnegative_fit(targets, keys.deltas[k][:, lm].reshape(len(k), -1))
    weights = Weights(values, keys.names, perf.track.fps)
    from helpers import rig_from_keyshapes

    rig = rig_from_keyshapes(keys, Delaunay(keys.neutral[:, :2]).simplices.astype(np.int64))
    return perf, keys, weights, poses, rig


def make_take_folder(folder: Path, *, with_video: bool = True, **options) -> Path:
    """Write take.json, track.npz, keys.json, weights.csv, animation.glb (and a video) into ``folder``."""
    from keyshape.io.gltf import write_glb
    from keyshape.io.keys_json import save_keys
    from keyshape.io.take import save_take_info
    from keyshape.io.track import save_track
    from keyshape.io.weights_csv import save_weights_csv

    perf, keys, weights, poses, rig = synthetic_take(**options)
    folder.mkdir(parents=True, exist_ok=True)
    video = folder / "take.mp4"
    if with_video:
        ramp = np.linspace(40, 200, 640).astype(np.uint8)
        frames = np.stack([np.dstack([np.tile(np.roll(ramp, 7 * i), (480, 1))] * 3)
                           for i in range(perf.track.n_frames)])
        write_video(video, frames, fps=25)
    save_track(perf.track, folder / "track.npz")
    save_keys(keys, folder / "keys.json")
    save_weights_csv(weights, folder / "weights.csv")
    write_glb(folder / "animation.glb", rig, weights, poses=poses)
    save_take_info(folder / "take.json", video=video, track=perf.track, keys=keys)
    return folder


def decode(path: Path) -> tuple[list[np.ndarray], float, int]:
    """(frames, average frame rate, frame count from the container) of an MP4, read back with PyAV."""
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        rate, count = float(stream.average_rate), int(stream.frames)
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
    return frames, rate, count


def uv_sphere(n_lat: int = 16, n_lon: int = 32, radii=(1.0, 0.7, 0.5)) -> tuple[np.ndarray, np.ndarray]:
    """An ellipsoid mesh: vertices (n, 3), faces (m, 3)."""
    theta = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    vertices = np.vstack([[0, 1, 0], ring, [0, -1, 0]]) * radii
    at = lambda i, j: 1 + i * n_lon + j % n_lon  # noqa: E731
    bottom = len(vertices) - 1
    faces = [[0, at(0, j + 1), at(0, j)] for j in range(n_lon)]
    faces += [[bottom, at(n_lat - 2, j), at(n_lat - 2, j + 1)] for j in range(n_lon)]
    for i in range(n_lat - 2):
        for j in range(n_lon):
            faces += [[at(i, j), at(i, j + 1), at(i + 1, j)], [at(i, j + 1), at(i + 1, j + 1), at(i + 1, j)]]
    return vertices, np.array(faces)


def silhouette(image: np.ndarray) -> np.ndarray:
    return np.abs(image.astype(int) - BACKGROUND_RGB).sum(axis=2) > 6


def gl_renderer(faces, width, height):
    try:
        return make_renderer(faces, width, height, backend="gl")
    except Exception as exc:  # noqa: BLE001 - no moderngl or no EGL here; moderngl raises a bare Exception
        pytest.skip(f"OpenGL on EGL unavailable: {exc}")


# --------------------------------------------------------------------------- renderers


@pytest.mark.parametrize("fov_deg", [None, 35.0])
def test_gl_and_numpy_renderers_agree(fov_deg):
    vertices, faces = uv_sphere()
    camera = frame_points(vertices, fov_deg=fov_deg, margin=1.3)
    with gl_renderer(faces, 160, 120) as gl, NumpyRenderer(faces, 160, 120) as cpu:
        a, b = gl.render(vertices, camera), cpu.render(vertices, camera)
    assert a.shape == b.shape == (120, 160, 3) and a.dtype == b.dtype == np.uint8
    sa, sb = silhouette(a), silhouette(b)
    assert 0.15 < sa.mean() < 0.8  # the mesh is in view and framed
    assert (sa & sb).sum() / (sa | sb).sum() > 0.97
    both = sa & sb
    assert np.abs(a[both].astype(int) - b[both]).mean() < 12  # smooth vs flat Lambert: close
    assert (a[~sa] == BACKGROUND_RGB).all() or np.abs(a[~sa].astype(int) - BACKGROUND_RGB).max() <= 1


@pytest.mark.parametrize("backend", ["gl", "numpy"])
def test_vertex_colours_paint_the_mesh(backend):
    vertices, faces = uv_sphere()
    camera = frame_points(vertices, margin=1.3)
    colours = np.where(vertices[:, [0]] > 0, [[0.9, 0.1, 0.1]], [[0.1, 0.1, 0.9]])  # red right, blue left
    with make_renderer(faces, 120, 120, n_vertices=len(vertices), backend=backend, colours=colours) as r:
        image = r.render(vertices, camera).astype(int)
    right, left = image[60, 80], image[60, 40]
    assert right[0] > 2 * right[2] and left[2] > 2 * left[0]
    with make_renderer(faces, 120, 120, n_vertices=len(vertices), backend=backend) as r:
        clay = r.render(vertices, camera).astype(int)
    assert abs(clay[60, 80, 0] - clay[60, 40, 0]) < 40  # without colours both sides are clay
    with pytest.raises(InputError, match="colours must be finite with shape"):
        make_renderer(faces, 8, 8, n_vertices=len(vertices), backend=backend, colours=colours[:5])


def test_renderers_show_the_front_and_light_it():
    vertices, faces = uv_sphere()
    camera = frame_points(vertices, margin=1.2)
    with NumpyRenderer(faces, 100, 100) as cpu:
        image = cpu.render(vertices, camera)
    # the light comes from the upper left, toward the viewer: the upper-left of the ellipsoid is brighter
    brightness = image.astype(float).sum(axis=2)
    assert brightness[35, 35] > brightness[65, 65]
    # the silhouette is as wide as the ellipsoid's x extent at orthographic scale
    columns = np.flatnonzero(silhouette(image).any(axis=0))
    assert abs((columns[-1] - columns[0] + 1) / 100 - 2 / (2 * 1.2)) < 0.04


def test_rasterizer_keeps_the_nearest_triangle_whatever_the_order():
    square = np.array([[0, 0, 0.5], [8, 0, 0.5], [0, 8, 0.5], [8, 8, 0.5], [0, 0, -0.5], [8, 0, -0.5],
                       [0, 8, -0.5], [8, 8, -0.5]], dtype=float)
    far, near = [[0, 1, 2], [1, 3, 2]], [[4, 5, 6], [5, 7, 6]]
    for faces in (far + near, near + far):
        ids = rasterize(square, np.array(faces), 8, 8)
        nearest = {i for i, f in enumerate(faces) if f in near}
        assert set(np.unique(ids)) <= nearest and (ids >= 0).all()


def test_rasterizer_skips_points_behind_the_camera_and_off_screen():
    tri = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0]], dtype=float)
    assert (rasterize(tri, np.array([[0, 1, 2]]), 4, 4, in_front=np.array([True, False, True])) == -1).all()
    assert (rasterize(tri + [100, 0, 0], np.array([[0, 1, 2]]), 4, 4) == -1).all()


def test_auto_falls_back_to_numpy_with_one_warning(monkeypatch):
    import keyshape.render.gl as gl_module

    def broken(*args, **kwargs):
        raise RuntimeError("no EGL display")

    monkeypatch.setattr(gl_module, "GLRenderer", broken)
    monkeypatch.setattr(render, "_warned", False)
    faces = np.array([[0, 1, 2]])
    with pytest.warns(RenderFallbackWarning, match="no EGL display"):
        first = make_renderer(faces, 8, 8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        second = make_renderer(faces, 8, 8)
    assert first.backend == second.backend == "numpy"
    with pytest.raises(RuntimeError, match="no EGL"):
        make_renderer(faces, 8, 8, backend="gl")
    with pytest.raises(ValueError, match="backend must be"):
        make_renderer(faces, 8, 8, backend="vulkan")


def test_video_writer_rate_size_and_count(tmp_path):
    path = tmp_path / "clip.mp4"
    with VideoWriter(path, 64, 48, 24000 / 1001) as out:
        for i in range(7):
            out.write(np.full((48, 64, 3), 30 * i, np.uint8))
    frames, rate, count = decode(path)
    assert len(frames) == count == 7 and frames[0].shape == (48, 64, 3)
    assert rate == pytest.approx(24000 / 1001, abs=1e-6)
    assert rate_of(30.0) == 30
    with pytest.raises(InputError, match="even"):
        VideoWriter(tmp_path / "odd.mp4", 63, 48, 25)


# --------------------------------------------------------------------------- the preview video


@pytest.fixture(scope="module")
def take_dir(tmp_path_factory) -> Path:
    return make_take_folder(tmp_path_factory.mktemp("take"))


@pytest.fixture(scope="module")
def preview(take_dir) -> tuple[Path, dict]:
    from keyshape.report import write_take_preview

    path = write_take_preview(take_dir, take_dir / "preview.mp4", progress=False, height=240)
    return path, {}


def test_preview_has_a_frame_per_track_frame_at_the_track_rate(take_dir, preview):
    from keyshape.io.track import load_track

    track = load_track(take_dir / "track.npz")
    frames, rate, count = decode(preview[0])
    assert len(frames) == count == track.n_frames
    assert rate == pytest.approx(track.fps, abs=1e-6)
    height, width = frames[0].shape[:2]
    assert height % 2 == 0 and width % 2 == 0
    assert width == 320 + 240  # 640×480 video scaled to 240 rows, beside a 240² character panel


def test_preview_character_moves_between_neutral_and_strong_expression(take_dir, preview):
    from keyshape.io.keys_json import load_keys
    from keyshape.io.weights_csv import load_weights_csv

    keys, weights = load_keys(take_dir / "keys.json"), load_weights_csv(take_dir / "weights.csv")
    frames, _, _ = decode(preview[0])
    strongest = int(np.nanargmax(np.nansum(weights.values, axis=1)))
    assert np.nansum(weights.values[strongest]) > 0.8 and np.nansum(weights.values[keys.neutral_frame]) < 0.1
    # the character panel (right of the 320-pixel source panel, above the weight strip)
    neutral = frames[keys.neutral_frame][40:240, 320:].astype(int)
    strong = frames[strongest][40:240, 320:].astype(int)
    changed = np.abs(neutral - strong).sum(axis=2) > 30
    assert changed.mean() > 0.01, "the character's face should move"
    # the head does not rotate in this take, so the silhouette barely changes: the motion is inside the face
    assert (silhouette(neutral.astype(np.uint8)) & changed).sum() > 0.8 * changed.sum()


def test_preview_draws_landmarks_in_region_colours(take_dir, preview):
    from keyshape.io.track import load_track
    from keyshape.render.draw import REGION_COLOURS

    frames, _, _ = decode(preview[0])
    track = load_track(take_dir / "track.npz")
    valid = int(np.flatnonzero(track.valid)[0])
    left = frames[valid][:240, :320].astype(int)
    for colour in REGION_COLOURS[:2]:  # upper, lower
        assert (np.abs(left - colour).sum(axis=2) < 60).sum() > 20


def test_preview_without_video_and_with_the_numpy_backend(tmp_path):
    from keyshape.render import render_preview
    from keyshape.schemes import head_rotations

    perf, keys, weights, poses, rig = synthetic_take(n_frames=12, n_missing=0, rotation_deg=20.0)
    path = render_preview(perf.track, weights, rig, tmp_path / "p.mp4", keys=keys, rotations=head_rotations(poses),
                          height=120, backend="numpy")
    frames, rate, count = decode(path)
    assert count == len(frames) == 12 and rate == pytest.approx(25.0)
    # the head turns: the character's silhouette changes from frame to frame
    panels = [silhouette(f[:120, -120:]) for f in frames]
    assert (panels[0] ^ panels[-1]).mean() > 0.005


def test_preview_rejects_mismatched_inputs(tmp_path):
    from keyshape.render.preview import render_preview

    perf, _, weights, _, rig = synthetic_take(n_frames=12, n_missing=0)
    short = Weights(weights.values[:5], weights.names, weights.fps)
    with pytest.raises(InputError, match="weights have 5 frames"):
        render_preview(perf.track, short, rig, tmp_path / "p.mp4")
    other = Rig(rig.vertices, rig.faces, rig.deltas[:1], ("x",))
    with pytest.raises(InputError, match="rig_weights"):
        render_preview(perf.track, weights, other, tmp_path / "p.mp4")
    assert not (tmp_path / "p.mp4").exists()


def test_preview_verb(take_dir, tmp_path):
    from keyshape.cli import main

    out = tmp_path / "verb.mp4"
    assert main(["preview", str(take_dir), "-o", str(out), "-q", "--height", "120"]) == 0
    frames, _, count = decode(out)
    assert count == len(frames) == 48
    assert main(["preview", str(tmp_path / "nowhere"), "-q"]) == 1


# --------------------------------------------------------------------------- the weight strip's labels

DEMO_KEYS = (*(f"upper_0{i}" for i in range(8)), "upper_03_mirror", "upper_07_mirror",
             *(f"lower_0{i}" for i in range(8)), *(f"lower_0{i}_mirror" for i in (1, 2, 3, 4, 6)))


def _check_labels_apart(strip, picture):
    """Every label inside its own cell, no two boxes touching, and no ink across a cell's edge."""
    from keyshape.render.draw import STRIP_BACKGROUND

    labelled = range(0, len(strip.names) - strip.stride + 1, strip.stride)
    assert [t for t, _ in strip.labels[: len(labelled)]] == [strip.short[i] for i in labelled]
    for (text, (x0, _, x1, _)), i in zip(strip.labels, labelled):
        assert i * strip.cell <= x0 and x1 <= (i + strip.stride) * strip.cell <= strip.width, (text, i, x0, x1)
    boxes = [box for _, box in strip.labels]
    for a in range(len(boxes)):
        for b in range(a + 1, len(boxes)):
            (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) = boxes[a], boxes[b]
            assert ax1 <= bx0 or bx1 <= ax0 or ay1 <= by0 or by1 <= ay0, (strip.labels[a], strip.labels[b])
    band = picture[strip.bar_bottom + 1: strip.bar_bottom + strip.font_size + 5]  # the row of bar labels
    inked = np.abs(band.astype(int) - STRIP_BACKGROUND).max(axis=-1) > 40
    for i in range(strip.stride, len(strip.names), strip.stride):
        x = int(i * strip.cell)
        assert not inked[:, x].any(), (i, strip.names[i])


def test_the_weight_strip_labels_are_distinct_and_apart():
    """Issue 36 item 8: the demo's 23 keys across the 1000-pixel preview: each bar's label (upper_03_mirror
    is "03m", under the "upper" region name) stays in its cell, none runs into the next, all distinct."""
    from keyshape.render.draw import WeightStrip

    regions = tuple(n.split("_")[0] for n in DEMO_KEYS)
    strip = WeightStrip(DEMO_KEYS, np.full((len(DEMO_KEYS), 3), 200, np.uint8), 1000, 96, regions=regions)
    picture = strip.draw(np.linspace(0, 1, len(DEMO_KEYS)))
    assert strip.stride == 1 and strip.font_size >= 10  # every bar labelled, readably
    texts = [t for t, _ in strip.labels]
    numbers = ["00", "01", "02", "03", "04", "05", "06", "07"]
    assert texts[: len(DEMO_KEYS)] == [*numbers, "03m", "07m", *numbers, "01m", "02m", "03m", "04m", "06m"]
    assert texts[len(DEMO_KEYS):] == ["upper  (m: mirrored)", "lower  (m: mirrored)"]
    # a label with its region is one key: (region under it, label) are distinct
    assert strip.groups == [("upper", 0, 10), ("lower", 10, 23)]
    (_, upper), (_, lower) = strip.labels[len(DEMO_KEYS):]
    assert upper[2] <= 10 * strip.cell <= lower[0]  # each region's name under its own keys
    named = [(strip.groups[0][0] if (box[0] + box[2]) / 2 < 10 * strip.cell else strip.groups[1][0], t)
             for t, box in strip.labels[: len(DEMO_KEYS)]]
    assert len(set(named)) == len(DEMO_KEYS)
    _check_labels_apart(strip, picture)


def test_a_crowded_strip_labels_every_kth_bar_apart():
    """52 rig names, none a key, in 640 pixels: whole names, as many as fit, none running into another."""
    from keyshape.render.draw import WeightStrip

    names = tuple(f"mouthStretch{i:02d}" for i in range(52))
    strip = WeightStrip(names, np.full((52, 3), 200, np.uint8), 640, 96)
    picture = strip.draw(np.zeros(52))
    assert strip.stride > 1 and all(t in names for t, _ in strip.labels)
    _check_labels_apart(strip, picture)
