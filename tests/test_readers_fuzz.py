"""Issue 34, "Must show": no input to a reader gives a traceback.

Each reader (track ``.npz``, ``keys.json``, ``weights.csv``, ``map.json``, ``take.json``, rigs as an
OBJ folder and a ``.glb``) is fed mutations of a valid file, drawn by hypothesis: bytes flipped,
cut or inserted; JSON leaves replaced by hostile values or dropped; track arrays replaced by
arrays of other shapes, types and values. Every input must either load or raise the project's own
error (:class:`~keyshape.exceptions.KeyshapeError`) as one line; anything else (an IndexError from
deep inside, a numpy overflow, a two-line message) fails the test.
"""

from __future__ import annotations

import io
import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from keyshape import Rig, Track, Weights
from keyshape.exceptions import KeyshapeError

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)


def _loads_or_one_line(read, path: Path) -> None:
    """``read(path)`` returns, or raises a KeyshapeError of one line naming something."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a reader may warn (InputWarning); it must not fail otherwise
            with np.errstate(all="raise"):  # no numpy overflow or invalid value behind the reader's back
                read(path)
    except KeyshapeError as error:
        text = str(error)
        assert text.strip() and "\n" not in text, repr(text)


# -- the valid files the mutations start from -------------------------------------------------------


def _track_bytes() -> bytes:
    from keyshape.io import save_track

    rng = np.random.default_rng(0)
    points = rng.normal(300, 20, size=(6, 5, 3))
    points[2] = np.nan
    scores = rng.uniform(0, 1, size=(6, 3)).astype(np.float32)
    scores[2] = np.nan
    track = Track(points, 30.0, (640, 480), scores, ("jawOpen", "_neutral", "eyeBlinkLeft"),
                  np.tile(np.eye(4), (6, 1, 1)), visibility=np.ones((6, 5)))
    return _saved(lambda p: save_track(track, p), "t.npz")


def _saved(write, name: str) -> bytes:
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / name
        write(path)
        return path.read_bytes()


KEYS = {"format": "keyshape-keys", "version": 1, "method": "spa", "n_landmarks": 4, "n_dims": 2,
        "neutral": {"take": "a.npz", "frame": 0},
        "regions": {"upper": {"indices": [0, 1], "keys": [{"name": "upper_00", "take": "a.npz", "frame": 3},
                                                          {"name": "upper_00_mirror", "take": "a.npz", "frame": 3,
                                                           "mirror_of": "upper_00"}]},
                    "lower": {"indices": [2, 3], "keys": [{"name": "lower_00", "take": "a.npz", "frame": 5}]}},
        "stable": [0, 1, 2, 3],
        "shapes": {"neutral": [[0, 0], [1, 0], [0, 1], [1, 1]], "upper_00": [[0, 0.2], [1, 0.2]],
                   "upper_00_mirror": [[0, 0.1], [1, 0.3]], "lower_00": [[0, 1.3], [1, 1.3]]}}
TAKE = {"format": "keyshape-take", "version": 1, "video": "/clips/take.mp4", "fps": 23.976, "n_frames": 472,
        "image_size": [640, 360], "neutral_frame": 12, "neutral_source": "/clips/rest.png",
        "files": {"track": "track.npz", "keys": "keys.json", "weights": "weights.csv", "animation": "animation.glb"},
        "written": ["animation.glb", "keys.json", "take.json", "track.npz", "weights.csv"]}
MAPS = [{"lower_03": {"jawOpen": 0.8, "mouthFunnel": 0.3}, "upper_01": {"browInnerUp": 1.0}},
        {"format": "keyshape-map", "version": 1, "gains": {"lower_03": {"jawOpen": -0.1, "mouthFunnel": 0.3}},
         "offset": {"jawOpen": 0.2}, "gaze": {"eyeLookInLeft": {"score": "eyeLookInLeft", "rest": 0.05}}},
        {"keys": ["a", "b"], "targets": ["jawOpen"], "matrix": [[0.5, 1.0]]}]


def _weights_text() -> str:
    from keyshape.io import save_weights_csv

    values = np.array([[0.0, 0.25], [np.nan, np.nan], [1.0, 0.5], [0.125, 4.5]])
    return _saved(lambda p: save_weights_csv(Weights(values, ("upper_00", "lower_00"), 30.0), p), "w.csv").decode()


def _rig() -> Rig:
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    deltas = np.zeros((2, 4, 3))
    deltas[0, 3, 2], deltas[1, 0, 1] = 0.1, -0.05
    return Rig(vertices, [[0, 1, 2], [1, 3, 2]], deltas, ("jawOpen", "smile"))


def _glb_bytes() -> bytes:
    from keyshape.io.gltf import write_glb

    rig = _rig()
    return _saved(lambda p: write_glb(p, rig, Weights(np.zeros((0, 2)), rig.names, 30.0)), "r.glb")


def _obj_text() -> str:
    from keyshape.io import save_obj_folder

    return _saved(lambda p: save_obj_folder(_rig(), p.parent) and None, "jawOpen.obj").decode()


# -- mutations --------------------------------------------------------------------------------------

HOSTILE = st.one_of(
    st.none(), st.booleans(), st.integers(-2**70, 2**70), st.sampled_from([1e300, -1e300, 1e-300, math.inf, -math.inf,
                                                                           math.nan, 0, -1, 99, 0.5, 5.0001]),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8), st.sampled_from(["", "neutral", "..", "/"]),
    st.lists(st.integers(-3, 6), max_size=5), st.lists(st.lists(st.floats(-10, 10), max_size=3), max_size=5),
    st.dictionaries(st.text(max_size=4), st.integers(-2, 2), max_size=3),
)


@st.composite
def byte_edits(draw, data: bytes) -> bytes:
    """``data`` with a few bytes replaced, a span cut out or bytes inserted, or cut short."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["flip", "cut", "insert", "truncate"]))
        at = draw(st.integers(0, max(len(out) - 1, 0)))
        if kind == "flip" and out:
            out[at] = draw(st.integers(0, 255))
        elif kind == "cut":
            del out[at : at + draw(st.integers(1, 64))]
        elif kind == "insert":
            out[at:at] = draw(st.binary(min_size=1, max_size=16))
        else:
            del out[at:]
    return bytes(out)


def _leaves(value, path=()):
    """Every (path, value) of a JSON document, containers included."""
    yield path, value
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _leaves(v, (*path, i))


@st.composite
def json_edits(draw, document) -> bytes:
    """``document`` with a few of its values replaced by hostile ones or dropped, as UTF-8 JSON
    (NaN and Infinity written as Python's json writes them)."""
    doc = json.loads(json.dumps(document))
    for _ in range(draw(st.integers(1, 3))):
        places = [p for p, _ in _leaves(doc) if p]
        if not places:
            break
        where = draw(st.sampled_from(places))
        parent = doc
        for step in where[:-1]:
            parent = parent[step]
        if draw(st.booleans()) and isinstance(parent, dict):
            del parent[where[-1]]
        else:
            parent[where[-1]] = draw(HOSTILE)
    if draw(st.integers(0, 9)) == 0:
        doc = draw(HOSTILE)  # not even an object
    return json.dumps(doc).encode()


ARRAYS = st.one_of(
    st.builds(np.full, st.lists(st.integers(0, 4), max_size=4).map(tuple),
              st.sampled_from([0.0, 1.0, np.nan, np.inf, -1e300, 2.0, -0.5, 1e7])),
    st.builds(lambda shape: np.zeros(shape, dtype=np.int64), st.lists(st.integers(0, 4), max_size=3).map(tuple)),
    st.builds(np.array, st.text(max_size=5)),
    st.builds(lambda n: np.arange(n, dtype=np.int64)[::-1], st.integers(0, 8)),
    st.sampled_from([np.array(True), np.array([1 + 2j]), np.array(99), np.array(2000.0), np.array(-3),
                     np.float64(30.0)]),
)


@st.composite
def npz_edits(draw, data: bytes) -> bytes:
    """The track file ``data`` with a few arrays replaced by others (any shape, type, values) or
    dropped, re-saved as an .npz."""
    with np.load(io.BytesIO(data)) as loaded:
        arrays = {k: loaded[k] for k in loaded.files}
    for _ in range(draw(st.integers(1, 3))):
        name = draw(st.sampled_from(sorted(arrays) + ["extra"]))
        if draw(st.integers(0, 3)) == 0:
            arrays.pop(name, None)
        elif name in arrays and arrays[name].size > 1 and draw(st.booleans()):  # one value of it
            array = np.array(arrays[name])
            index = draw(st.integers(0, array.size - 1))
            if array.dtype.kind in "fiu":
                array = array.astype(float)
                array.reshape(-1)[index] = draw(st.sampled_from([np.nan, np.inf, -1.0, 2.0, 1e7, 1e300]))
            arrays[name] = array
        else:
            arrays[name] = draw(ARRAYS)
    out = io.BytesIO()
    np.savez(out, **arrays)
    return out.getvalue()


# -- the readers ------------------------------------------------------------------------------------

TRACK, WEIGHTS, GLB, OBJ = _track_bytes(), _weights_text(), _glb_bytes(), _obj_text()


def _write(tmp_path_factory, name: str, data: bytes) -> Path:
    path = tmp_path_factory.mktemp("fuzz") / name
    path.write_bytes(data)
    return path


def _load_track(path):
    from keyshape.io import load_track, open_track

    load_track(path)
    opened = open_track(path)  # the streamed reader checks the points as it reads them
    if opened is not None:
        for _ in opened.chunks(np.arange(opened.n_landmarks), frames=2):
            pass


@FUZZ
@given(st.one_of(npz_edits(TRACK), byte_edits(TRACK)))
def test_track_files(tmp_path_factory, data):
    _loads_or_one_line(_load_track, _write(tmp_path_factory, "t.npz", data))


@FUZZ
@given(st.one_of(json_edits(KEYS), byte_edits(json.dumps(KEYS).encode())))
def test_key_files(tmp_path_factory, data):
    from keyshape.io import load_keys

    _loads_or_one_line(load_keys, _write(tmp_path_factory, "keys.json", data))


@FUZZ
@given(st.one_of(byte_edits(WEIGHTS.encode()),
                 st.lists(st.tuples(st.integers(0, 5), st.integers(0, 3), st.sampled_from(
                     ["", "nan", "inf", "-1", "5.5", "1e300", "x", '"1"', " 0.5 ", "2", "0x1", "1,2"])),
                     min_size=1, max_size=4).map(lambda edits: _cell_edits(WEIGHTS, edits).encode())))
def test_weights_files(tmp_path_factory, data):
    from keyshape.io import load_weights_csv

    _loads_or_one_line(load_weights_csv, _write(tmp_path_factory, "w.csv", data))


def _cell_edits(text: str, edits) -> str:
    """``text`` (a CSV) with cell (row, column) of each edit replaced."""
    rows = [line.split(",") for line in text.splitlines()]
    for row, column, value in edits:
        if row < len(rows) and column < len(rows[row]):
            rows[row][column] = value
    return "\n".join(",".join(r) for r in rows) + "\n"


@FUZZ
@given(st.one_of(*(json_edits(m) for m in MAPS), byte_edits(json.dumps(MAPS[1]).encode())),
       st.sampled_from([None, ["jawOpen", "mouthFunnel", "browInnerUp", "eyeLookInLeft"]]))
def test_mapping_files(tmp_path_factory, data, targets):
    from keyshape.targets import Mapping

    _loads_or_one_line(lambda p: Mapping.from_file(p, targets=targets), _write(tmp_path_factory, "map.json", data))


@FUZZ
@given(st.one_of(json_edits(TAKE), byte_edits(json.dumps(TAKE).encode())))
def test_take_files(tmp_path_factory, data):
    from keyshape.io import load_take_info

    folder = _write(tmp_path_factory, "take.json", data).parent
    _loads_or_one_line(load_take_info, folder)


@FUZZ
@given(byte_edits(GLB))
def test_glb_rigs(tmp_path_factory, data):
    from keyshape.io import load_rig

    _loads_or_one_line(load_rig, _write(tmp_path_factory, "rig.glb", data))


@FUZZ
@given(byte_edits(OBJ.encode()), st.sampled_from(["folder", "file"]))
def test_obj_rigs(tmp_path_factory, data, form):
    from keyshape.io import load_rig, save_obj_folder

    folder = tmp_path_factory.mktemp("rig")
    save_obj_folder(_rig(), folder)
    (folder / "jawOpen.obj").write_bytes(data)
    _loads_or_one_line(load_rig, folder if form == "folder" else folder / "jawOpen.obj")


@pytest.mark.parametrize("name, data", [("t.npz", TRACK), ("w.csv", WEIGHTS.encode()), ("rig.glb", GLB)])
def test_the_unmutated_files_load(tmp_path, name, data):
    """The starting points are valid: each mutation is measured against a file that loads."""
    from keyshape.io import load_rig, load_track, load_weights_csv

    path = tmp_path / name
    path.write_bytes(data)
    {"t.npz": load_track, "w.csv": load_weights_csv, "rig.glb": load_rig}[name](path)
