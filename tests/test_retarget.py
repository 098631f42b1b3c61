import numpy as np
import pytest

from keyshape.containers import Rig, Weights
from keyshape.exceptions import InputError, RigError
from keyshape.targets import Mapping, retarget


@pytest.fixture
def weights():
    rng = np.random.default_rng(0)
    return Weights(rng.random((12, 3)), ("upper_00", "lower_00", "lower_01"), fps=25)


def test_identity_mapping_is_a_no_op(weights):
    out = retarget(weights, Mapping.by_name(weights.names, weights.names))
    np.testing.assert_array_equal(out.values, weights.values)
    assert out.names == weights.names and out.fps == weights.fps


def test_by_name_follows_rig_order(weights):
    rig_names = ("lower_01", "upper_00", "lower_00")
    out = retarget(weights, Mapping.by_name(weights, rig_names))
    assert out.names == rig_names
    np.testing.assert_array_equal(out.values, weights.values[:, [2, 0, 1]])


def test_by_name_accepts_a_rig():
    rig = Rig(np.eye(3), [[0, 1, 2]], np.zeros((2, 3, 3)), ("a", "b"))
    assert Mapping.by_name(["b", "a"], rig).targets == ("a", "b")


def test_missing_names_error_lists_them(weights):
    with pytest.raises(RigError, match=r"no same-named rig target: \['lower_00', 'lower_01'\]"):
        Mapping.by_name(weights.names, ["upper_00", "Angry"], allow_extra=True)


def test_extra_targets_error_lists_them_unless_allowed(weights):
    targets = weights.names + ("Angry", "Sad")
    with pytest.raises(RigError, match=r"no same-named key: \['Angry', 'Sad'\].*allow_extra=True"):
        Mapping.by_name(weights.names, targets)
    out = retarget(weights, Mapping.by_name(weights.names, targets, allow_extra=True))
    np.testing.assert_array_equal(out.values[:, :3], weights.values)
    np.testing.assert_array_equal(out.values[:, 3:], 0.0)


def test_from_dict_gains(weights):
    mapping = Mapping.from_dict(
        {"upper_00": {"Surprised": 1.0}, "lower_01": {"Sad": 0.5, "Angry": 2.0}}
    )
    assert mapping.sources == ("upper_00", "lower_01")
    assert mapping.targets == ("Surprised", "Sad", "Angry")
    out = retarget(weights, mapping)
    np.testing.assert_allclose(out.values[:, 0], weights.values[:, 0])
    np.testing.assert_allclose(out.values[:, 1], 0.5 * weights.values[:, 2])
    np.testing.assert_allclose(out.values[:, 2], 2.0 * weights.values[:, 2])
    assert Mapping.from_dict(mapping.to_dict()).matrix.tolist() == mapping.matrix.tolist()


def test_from_dict_sums_keys_driving_one_target(weights):
    mapping = Mapping.from_dict({"lower_00": {"jaw": 1.0}, "lower_01": {"jaw": 1.0}})
    out = retarget(weights, mapping)
    np.testing.assert_allclose(out.values[:, 0], weights.values[:, 1] + weights.values[:, 2])


def test_from_dict_in_rig_order_and_unknown_targets():
    mapping = Mapping.from_dict({"k": {"Sad": 1.0}}, targets=["Angry", "Surprised", "Sad"])
    assert mapping.matrix[:, 0].tolist() == [0.0, 0.0, 1.0]
    with pytest.raises(RigError, match=r"does not have: \['Happy'\]"):
        Mapping.from_dict({"k": {"Happy": 1.0}}, targets=["Angry", "Sad"])


@pytest.mark.parametrize("gain", [-1.0, float("nan"), "much"])
def test_bad_gains_are_rejected(gain):
    with pytest.raises(InputError, match="gain for key 'k' -> target 't'"):
        Mapping.from_dict({"k": {"t": gain}})


def test_matrix_shape_and_sign_are_checked():
    with pytest.raises(InputError, match=r"shape \(n_targets, n_keys\) = \(1, 2\); got \(2, 1\)"):
        Mapping(np.ones((2, 1)), ("a", "b"), ("t",))
    with pytest.raises(InputError, match=">= 0"):
        Mapping(-np.ones((1, 1)), ("a",), ("t",))


def test_nan_frames_become_neutral(weights):
    values = weights.values.copy()
    values[3] = np.nan
    out = retarget(Weights(values, weights.names, weights.fps), Mapping.by_name(weights, weights))
    np.testing.assert_array_equal(out.values[3], 0.0)
    assert np.isfinite(out.values).all()


def test_weights_missing_mapping_keys(weights):
    with pytest.raises(RigError, match=r"do not have: \['mouth_02'\]"):
        retarget(weights, Mapping.from_dict({"mouth_02": {"Sad": 1.0}}))


def test_matrix_is_read_only(weights):
    mapping = Mapping.by_name(weights, weights)
    with pytest.raises(ValueError):
        mapping.matrix[0, 0] = 2.0


# ---------------------------------------------------------------- mapping files

import json  # noqa: E402


def _write(path, data):
    path.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return path


def test_mapping_file_plain_wrapped_and_matrix(weights, tmp_path):
    gains = {"lower_00": {"jawOpen": 0.8, "mouthFunnel": 0.3}, "upper_00": {"browInnerUp": 1.0}}
    plain = Mapping.from_file(_write(tmp_path / "plain.json", gains))
    assert plain.to_dict() == gains
    wrapped = Mapping.from_file(plain.save(tmp_path / "saved.json"))
    np.testing.assert_array_equal(wrapped.matrix, plain.matrix)
    assert json.loads((tmp_path / "saved.json").read_text())["format"] == "keyshape-map"
    matrix = {"keys": ["lower_00", "upper_00"], "targets": ["jawOpen", "mouthFunnel", "browInnerUp"],
              "matrix": [[0.8, 0.0], [0.3, 0.0], [0.0, 1.0]]}
    assert Mapping.from_file(_write(tmp_path / "m.json", matrix)).to_dict() == gains
    out = retarget(weights, plain)
    np.testing.assert_allclose(out.values[:, 0], 0.8 * weights.values[:, 1])


def test_mapping_file_in_rig_order(tmp_path):
    path = _write(tmp_path / "map.json", {"k": {"Sad": 0.5}})
    mapping = Mapping.from_file(path, targets=("Angry", "Surprised", "Sad"))
    assert mapping.targets == ("Angry", "Surprised", "Sad") and mapping.matrix[:, 0].tolist() == [0, 0, 0.5]


@pytest.mark.parametrize("content, message", [
    ("{not json", r"bad\.json: not a readable JSON mapping"),
    ("[1, 2]", r"bad\.json: expected a JSON object \{key: \{target: gain"),
    ('{"k": 0.5}', r"bad\.json: key 'k' must map to an object"),
    ('{"k": {"t": -1}}', r"bad\.json: gain for key 'k' -> target 't' must be a finite number in 0\.\.100"),
    ('{"keys": ["a"], "targets": ["t"], "matrix": [[1, 2]]}', r"bad\.json: matrix must have shape"),
])
def test_bad_mapping_files_name_the_file(tmp_path, content, message):
    with pytest.raises(InputError, match=message):
        Mapping.from_file(_write(tmp_path / "bad.json", content))


def test_mapping_file_naming_targets_the_rig_lacks(tmp_path):
    path = _write(tmp_path / "map.json", {"k": {"Happy": 1.0, "Sad": 1.0}})
    with pytest.raises(RigError, match=r"map\.json: .*does not have: \['Happy'\]"):
        Mapping.from_file(path, targets=("Angry", "Sad"))
    with pytest.raises(InputError, match="mapping file not found"):
        Mapping.from_file(tmp_path / "missing.json")


def test_from_dict_with_given_sources():
    mapping = Mapping.from_dict({"b": {"t": 1.0}}, sources=["a", "b"])
    assert mapping.sources == ("a", "b") and mapping.matrix.tolist() == [[0.0, 1.0]]
    with pytest.raises(InputError, match=r"keys \['c'\] not among the sources"):
        Mapping.from_dict({"c": {"t": 1.0}}, sources=["a", "b"])


def test_offset_mapping_starts_from_the_neutral_pose(tmp_path):
    """A neutral that smiles: keys with less smile lower it (gains down to -offset); weights stay >= 0."""
    m = Mapping.from_dict({"calm": {"smile": -0.4}, "grin": {"smile": 0.5, "jawOpen": 0.2}},
                          targets=["smile", "jawOpen"], offset={"smile": 0.4})
    assert m.offset.tolist() == [0.4, 0.0]
    w = Weights(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]), ("calm", "grin"), fps=30)
    out = retarget(w, m).values
    np.testing.assert_allclose(out, [[0.4, 0.0], [0.0, 0.0], [0.9, 0.2], [0.5, 0.2]])
    again = Mapping.from_file(m.save(tmp_path / "map.json"), targets=["jawOpen", "smile"])
    np.testing.assert_allclose(retarget(w, again).values, out[:, ::-1])
    assert json.loads((tmp_path / "map.json").read_text())["offset"] == {"smile": 0.4}


def test_gains_below_minus_the_offset_are_refused():
    with pytest.raises(InputError, match=r"must be a finite number in -0.4 \(its offset\)\.\.100"):
        Mapping.from_dict({"calm": {"smile": -0.5}}, offset={"smile": 0.4})
    with pytest.raises(InputError, match=">= 0"):
        Mapping(np.array([[-0.5]]), ["calm"], ["smile"], offset=[0.4])
    with pytest.raises(InputError, match="offset must be 1 finite numbers >= 0"):
        Mapping(np.array([[0.5]]), ["calm"], ["smile"], offset=[-0.1])
