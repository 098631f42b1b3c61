"""A `.vrma` keyshape writes, played by three-vrm and three-vrm-animation (npm, tools/node_modules) in
Debian's headless Chromium (issue 37): `keyshape run CLIP --rig AVATAR.vrm` on the hand-written
avatars (VRM 1.0 and 0.x, standard and perfect sync), the page (tools/vrma_player/) loads the avatar
and the take's animation.vrma, sets the mixer to a frame's time and renders. On the clip's most open
frame the mouth morph is driven as the file says and the face's pixels change; on its neutral frame
the mouth is shut and the picture is the avatar's rest; the head and the look-at turn as the file says."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_vrma import read_vrma
from vrm_avatars import FACE_TRANSLATION, make_vrm

TOOLS = Path(__file__).resolve().parent.parent / "tools"
ORIGIN = "http://vrma.test"
_TYPES = {".html": "text/html", ".js": "text/javascript", ".mjs": "text/javascript", ".json": "application/json"}
KINDS = [("1.0", False), ("0.x", False), ("1.0", True), ("0.x", True)]
FRAMES = 90  # of the clip, for each of the four runs


def _need_packages():
    missing = [name for name in ("three", "@pixiv/three-vrm", "@pixiv/three-vrm-animation")
               if not (TOOLS / "node_modules" / name / "package.json").is_file()]
    if missing:
        pytest.fail(f"tools/node_modules lacks {missing}: npm ci --prefix tools", pytrace=False)


@pytest.fixture(scope="module")
def takes(demo_clip, tmp_path_factory):
    """{(version, perfect_sync): (avatar path, take folder)}: `keyshape run` on the clip's first frames for
    each avatar, with the key set a first plain run found there, mapped onto the avatar: the key that
    opens the mouth most (inner lips, MediaPipe 13 and 14, furthest apart) drives `aa` (and, perfect
    sync, `jawOpen`), the next one `oh` at 0.6, an upper-face key the blink."""
    from keyshape.cli import main
    from keyshape.io import load_keys

    root = tmp_path_factory.mktemp("vrma_takes")
    assert main(["run", str(demo_clip), "--end", str(FRAMES), "--no-preview", "-o", str(root / "plain"), "-q"]) == 0
    keys = load_keys(root / "plain" / "keys.json")
    lower = [keys.names[k] for k in sorted(keys.keys_of("lower"), key=lambda k: -_opening(keys, k))]
    upper = [keys.names[k] for k in keys.keys_of("upper")]
    out = {}
    for version, sync in KINDS:
        name = f"{version}{'-ps' if sync else ''}"
        avatar = make_vrm(root / f"{name}.vrm", version, perfect_sync=sync, skeleton=True)
        aa, oh, blink = ("aa", "oh", "blink") if version == "1.0" else ("A", "O", "Blink")
        mapping = {lower[0]: {aa: 1.0, **({"jawOpen": 0.8} if sync else {})}, lower[1]: {oh: 0.6},
                   upper[0]: {blink: 1.0}}
        (root / f"{name}.json").write_text(json.dumps(mapping))
        assert main(["run", str(demo_clip), "--keys", str(root / "plain" / "keys.json"), "--rig", str(avatar.path),
                     "--map", str(root / f"{name}.json"), "--end", str(FRAMES), "--no-preview", "-o",
                     str(root / name), "-q"]) == 0
        out[version, sync] = avatar.path, root / name
    return out


def _opening(keys, index: int) -> float:
    """How far key ``index`` parts the inner lips (MediaPipe 13 above, 14 below; image y down), in the
    neutral's units."""
    delta = keys.deltas[index]
    return float(delta[14, 1] - delta[13, 1])


def _page(browser, files: dict[str, Path]):
    """A page of the player, tools/ served at its root and ``files`` at their names."""
    page = browser.new_page(viewport={"width": 256, "height": 256})
    errors = []
    page.on("pageerror", lambda error: errors.append(str(error)))

    def serve(route):
        name = route.request.url.removeprefix(ORIGIN)
        path = files.get(name) or TOOLS / name.lstrip("/")
        if not path.is_file() or (path not in files.values() and TOOLS not in path.resolve().parents):
            return route.fulfill(status=404, body="")
        return route.fulfill(path=str(path), content_type=_TYPES.get(path.suffix, "application/octet-stream"))

    page.route(f"{ORIGIN}/**", serve)
    page.goto(f"{ORIGIN}/vrma_player/index.html")
    page.wait_for_function("window.ready === true", timeout=60_000)
    return page, errors


def _picture(page) -> np.ndarray:
    from io import BytesIO

    from PIL import Image

    return np.asarray(Image.open(BytesIO(page.screenshot())).convert("RGB"), dtype=float)


@pytest.mark.slow
@pytest.mark.parametrize("version, sync", KINDS, ids=["1.0", "0.x", "1.0-perfect-sync", "0.x-perfect-sync"])
def test_three_vrm_plays_the_take(browser, takes, version, sync):
    _need_packages()
    avatar, take = takes[version, sync]
    extension, tracks, _ = read_vrma(take / "animation.vrma")
    aa_node = extension["expressions"]["preset"]["aa"]["node"]
    times, moved = tracks[aa_node, "translation"]
    aa = moved[:, 0]
    oh = tracks[extension["expressions"]["preset"]["oh"]["node"], "translation"][1][:, 0]
    jaw = tracks[extension["expressions"]["custom"]["jawOpen"]["node"], "translation"][1][:, 0] if sync else 0 * aa
    mouth = aa + 0.5 * oh  # the mouthOpen morph: aa binds it at 1, oh at 0.5 (vrm_avatars.EXPRESSIONS); ih is 0
    from keyshape.io import load_keys, load_weights_csv

    weights = load_weights_csv(take / "weights.csv")
    opened = int(np.argmax(mouth))  # the clip's most open mouth
    shut = int(np.flatnonzero(weights.frame_index == load_keys(take / "keys.json").neutral_frame)[0])
    assert mouth[opened] > 0.3 and mouth[shut] + jaw[shut] < 0.05, (mouth[opened], mouth[shut], jaw[shut])

    page, errors = _page(browser, {"/files/avatar.vrm": avatar, "/files/take.vrma": take / "animation.vrma"})
    focus = [0.0, FACE_TRANSLATION[1] + 0.025, FACE_TRANSLATION[2]]
    info = page.evaluate("([f, d]) => window.load('/files/avatar.vrm', '/files/take.vrma', f, d)", [focus, 0.3])
    assert info["metaVersion"] == ("1" if version == "1.0" else "0")
    assert info["duration"] == pytest.approx(float(times[-1]), abs=1e-4)
    page.evaluate("window.rest()")
    rest = _picture(page)
    states, pictures = {}, {}
    for label, frame in (("open", opened), ("shut", shut)):
        states[label] = page.evaluate("(t) => window.pose(t)", float(times[frame]))
        pictures[label] = _picture(page)
    assert not errors, errors

    for label, frame in (("open", opened), ("shut", shut)):
        weights, morphs = states[label]["weights"], states[label]["morphs"]
        assert weights["aa"] == pytest.approx(float(aa[frame]), abs=1e-4)  # the .vrma's preset, on either version
        assert weights["oh"] == pytest.approx(float(oh[frame]), abs=1e-4)
        if sync:
            assert weights["jawOpen"] == pytest.approx(float(jaw[frame]), abs=1e-4)
        (open_morph,) = [v for k, v in morphs.items() if k.endswith("/mouthOpen")]
        assert open_morph == pytest.approx(float(mouth[frame]), abs=1e-3)
    assert states["open"]["head"] != [0, 0, 0, 1]  # the head bone turns with the take's poses
    _, gaze = tracks[extension["lookAt"]["node"], "rotation"]
    for label, frame in (("open", opened), ("shut", shut)):  # the look-at's yaw and pitch, in degrees
        yaw, pitch, _ = np.degrees(Rotation.from_quat(gaze[frame]).as_euler("YXZ"))
        assert states[label]["look"] == pytest.approx([yaw, pitch], abs=1e-3)
    # the pixels: the open mouth moves the face; the shut frame looks like the avatar at rest
    face = np.abs(rest - rest[0, 0]).sum(axis=2) > 30  # the face's pixels, against the background
    assert face.mean() > 0.05, "the face is not in the picture"
    opened_change = np.abs(pictures["open"] - rest).sum(axis=2)
    shut_change = np.abs(pictures["shut"] - rest).sum(axis=2)
    assert (opened_change > 30).mean() > 0.01, "the open mouth changed no pixel"
    assert (opened_change > 30).sum() > 10 * max((shut_change > 30).sum(), 1)
    page.close()
