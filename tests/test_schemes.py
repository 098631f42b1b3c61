import json

import numpy as np
import pytest

from keyshape.exceptions import InputError
from keyshape.schemes import face_triangles, mediapipe_scheme, resolve_regions, stable_points


def test_json_matches_mediapipe_connections():
    from mediapipe.tasks.python import vision

    C = vision.FaceLandmarksConnections
    scheme = mediapipe_scheme()
    lips = sorted({i for c in C.FACE_LANDMARKS_LIPS for i in (c.start, c.end)})
    assert scheme["contours"]["lips"] == lips
    edges = {tuple(sorted((c.start, c.end))) for c in C.FACE_LANDMARKS_TESSELATION}
    for tri in face_triangles()[:200]:
        a, b, c = sorted(tri)
        assert {(a, b), (a, c), (b, c)} <= edges


@pytest.mark.parametrize("n", [468, 478, 68])
@pytest.mark.parametrize("scheme", ["upper-lower", "eyes"])
def test_regions_are_disjoint_and_in_range(n, scheme):
    regions = resolve_regions(scheme, n)
    seen = np.concatenate(list(regions.values()))
    assert len(seen) == len(set(seen.tolist()))
    assert seen.max() < n


def test_upper_lower_separates_eyes_from_mouth():
    scheme = mediapipe_scheme()["contours"]
    regions = resolve_regions("upper-lower", 478)
    assert set(scheme["left_eye"]) <= set(regions["upper"].tolist())
    assert set(scheme["lips"]) <= set(regions["lower"].tolist())
    # irises carry gaze, which is not blended
    assert not set(scheme["left_iris"]) & set(regions["upper"].tolist())


def test_stable_points_avoid_mouth_and_jaw():
    regions = resolve_regions("upper-lower", 478)
    assert not set(stable_points(478).tolist()) & set(regions["lower"].tolist())


def test_regions_file(tmp_path):
    path = tmp_path / "regions.json"
    path.write_text(json.dumps({"a": [0, 1, 2], "b": [3, 4]}))
    regions = resolve_regions(path, 5)
    assert regions["b"].tolist() == [3, 4]
    with pytest.raises(InputError, match=r"indices must be in 0\.\.3"):
        resolve_regions(path, 4)


def test_unknown_scheme_for_odd_track():
    with pytest.raises(InputError, match="use --regions whole"):
        resolve_regions("upper-lower", 30)
    assert resolve_regions("whole", 30)["whole"].size == 30
