"""The browser viewer (``keyshape view``): its server, its command, and the page in a real browser.

The page runs in Debian's headless Chromium (``apt-get install chromium``) driven by the
Python ``playwright`` package pointed at that browser; no browser is ever downloaded. A
missing browser or package is a failure, not a skip: CI installs both.
"""

from __future__ import annotations

import http.client
import io
import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from keyshape.cli import main
from keyshape.containers import Poses, Rig, Weights
from keyshape.exceptions import InputError
from keyshape.io.gltf import read_glb_animation, write_glb
from keyshape.io.weights_csv import save_weights_csv
from keyshape.viewer.server import RangeNotSatisfiable, load_take, make_server, parse_range

from conftest import write_video

ARTIFACTS = Path(os.environ.get("KEYSHAPE_TEST_ARTIFACTS", Path(__file__).parent / "artifacts"))
TOLERANCE = 1e-4  # the CSV holds 6 decimals, the .glb float32

# --------------------------------------------------------------------------- takes


def _csv_weights(folder: Path) -> tuple[list[str], np.ndarray]:
    """Names and ``(n_frames, n_keys)`` values of weights.csv, NaN cells (no estimate) as 0."""
    lines = (folder / "weights.csv").read_text().splitlines()
    names = lines[0].split(",")[2:]
    rows = [[float(c) if c else 0.0 for c in line.split(",")[2:]] for line in lines[1:] if line]
    return names, np.array(rows)


def _write_take(folder: Path, *, n_frames: int = 20, fps: float = 10.0, video: bool = True) -> Path:
    """A small take with known answers: 3 targets (NaN frames 5-6), a turning head, and a video
    whose frame k is uniformly grey at level 12·k."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(6)
    vertices = np.array([[-0.1, -0.1, 0.0], [0.1, -0.1, 0.0], [0.1, 0.1, 0.0], [-0.1, 0.1, 0.0]])
    rig = Rig(vertices, [[0, 1, 2], [0, 2, 3]], rng.normal(0, 0.02, (3, 4, 3)),
              ("mouth_open", "mouth_smile", "eyes_blink"))
    values = rng.uniform(0, 1, (n_frames, 3))
    values[5:7] = np.nan
    weights = Weights(values, rig.names, fps)
    rotations = Rotation.from_euler("z", 2.0 * np.arange(n_frames)[:, None], degrees=True).as_matrix()
    poses = Poses(rotations, np.zeros((n_frames, 3)), np.ones(n_frames))
    write_glb(folder / "animation.glb", rig, weights, poses=poses)
    save_weights_csv(weights, folder / "weights.csv")
    clip = folder / "clip.mp4"
    if video:
        grey = np.repeat(12 * np.arange(n_frames, dtype=np.uint8), 48 * 64 * 3)
        write_video(clip, grey.reshape(n_frames, 48, 64, 3), fps=int(fps))
    info = {"format": "keyshape-take", "version": 1, "video": str(clip), "fps": fps,
            "n_frames": n_frames, "image_size": [64, 48], "neutral_frame": 0,
            "files": {"weights": "weights.csv", "animation": "animation.glb"}}
    (folder / "take.json").write_text(json.dumps(info))
    return folder


@pytest.fixture(scope="module")
def small_take(tmp_path_factory) -> Path:
    return _write_take(tmp_path_factory.mktemp("small-take"))


@pytest.fixture(scope="session")
def demo_take(demo_out) -> Path:
    """An output folder of the real `keyshape demo` (shared with the other tests)."""
    return demo_out


class _Served:
    """A viewer server running in a thread, for the duration of a ``with`` block."""

    def __init__(self, folder: Path):
        self.server = make_server(folder, port=0)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def __enter__(self):
        self.thread.start()
        return self.server

    def __exit__(self, *exc):
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(5)


def _get(server, path: str, headers: dict | None = None) -> tuple[int, dict, bytes]:
    host, port = server.server_address[:2]
    conn = http.client.HTTPConnection(host, port, timeout=10)
    try:
        conn.request("GET", path, headers=headers or {})
        response = conn.getresponse()
        return response.status, dict(response.getheaders()), response.read()
    finally:
        conn.close()


# --------------------------------------------------------------------------- server


@pytest.mark.parametrize(("header", "expected"), [
    ("bytes=0-99", (0, 99)), ("bytes=900-", (900, 999)), ("bytes=-100", (900, 999)),
    ("bytes=-5000", (0, 999)), ("bytes=10-5000", (10, 999)), ("bytes=999-999", (999, 999)),
    (None, None), ("", None), ("bytes=0-1,5-9", None), ("items=0-9", None), ("bytes=9-2", None),
    ("bytes=-", None),
])
def test_parse_range(header, expected):
    assert parse_range(header, 1000) == expected


@pytest.mark.parametrize("header", ["bytes=1000-", "bytes=5000-6000", "bytes=-0"])
def test_parse_range_outside_the_file(header):
    with pytest.raises(RangeNotSatisfiable):
        parse_range(header, 1000)


def test_load_take(small_take):
    take = load_take(small_take)
    assert take.fps == 10.0 and take.n_frames == 20 and take.video == small_take / "clip.mp4"
    assert set(take.files) == {"weights.csv", "animation.glb"}
    page = take.as_json()
    assert page["video"] == "/media/video" and page["animation"] == "/media/animation.glb"


def test_load_take_errors(tmp_path, small_take):
    with pytest.raises(InputError, match=r"no take\.json"):
        load_take(tmp_path)
    folder = tmp_path / "take"
    folder.mkdir()
    info = json.loads((small_take / "take.json").read_text())
    (folder / "take.json").write_text(json.dumps(info))
    with pytest.raises(InputError, match=r"no animation\.glb here"):
        load_take(folder)
    (folder / "animation.glb").write_bytes((small_take / "animation.glb").read_bytes())
    (folder / "take.json").write_text(json.dumps({**info, "fps": 0}))
    with pytest.raises(InputError, match="fps must be a positive number; got 0"):
        load_take(folder)
    (folder / "take.json").write_text(json.dumps({**info, "video": str(tmp_path / "gone.mp4")}))
    assert load_take(folder).video is None  # the page then plays the character alone


def test_server_routes_and_ranges(small_take):
    video = (small_take / "clip.mp4").read_bytes()
    with _Served(small_take) as server:
        status, headers, body = _get(server, "/")
        assert status == 200 and b'src="/static/viewer.js"' in body
        status, headers, body = _get(server, "/static/viewer.js")
        assert status == 200 and headers["Content-Type"] == "text/javascript" and len(body) > 100_000
        status, _, body = _get(server, "/api/take")
        assert status == 200 and json.loads(body)["n_frames"] == 20
        status, headers, body = _get(server, "/media/video")
        assert (status, body, headers["Accept-Ranges"]) == (200, video, "bytes")
        status, headers, body = _get(server, "/media/video", {"Range": "bytes=100-199"})
        assert (status, body) == (206, video[100:200])
        assert headers["Content-Range"] == f"bytes 100-199/{len(video)}"
        status, headers, body = _get(server, "/media/video", {"Range": f"bytes={len(video)}-"})
        assert (status, headers["Content-Range"], body) == (416, f"bytes */{len(video)}", b"")
        status, headers, _ = _get(server, "/media/animation.glb")
        assert status == 200 and headers["Content-Type"] == "model/gltf-binary"
        assert _get(server, "/api/take", {"Host": "localhost"})[0] == 200
        assert _get(server, "/api/take", {"Host": "rebound.example:80"})[0] == 403
        for path in ("/media/take.json", "/media/../take.json", "/static/../server.py",
                     "/static/%2e%2e/server.py", "/media/clip.mp4", "/nothing"):
            assert _get(server, path)[0] == 404, path


def test_view_command(small_take):
    """`keyshape view` serves until interrupted and says where."""
    proc = subprocess.Popen([sys.executable, "-m", "keyshape", "view", str(small_take), "--port", "0",
                             "--no-browser"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert "20 frames at 10 fps, clip.mp4" in proc.stdout.readline()
        line = proc.stdout.readline()
        assert line.startswith("viewer at http://127.0.0.1:"), line
        host_port = line.split("http://")[1].split("/")[0]
        conn = http.client.HTTPConnection(host_port, timeout=10)
        conn.request("GET", "/api/take")
        assert json.loads(conn.getresponse().read())["fps"] == 10.0
        conn.close()
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert "viewer stopped" in out


def test_view_command_falls_back_to_a_free_port(small_take, monkeypatch):
    from keyshape.cli import view

    with _Served(small_take) as busy:
        monkeypatch.setattr(view, "DEFAULT_PORT", busy.server_address[1])
        with view._bind(make_server, small_take, None) as server:
            assert server.server_address[1] not in (0, busy.server_address[1])


def test_view_command_errors(tmp_path, small_take, capsys):
    assert main(["view", str(tmp_path), "--no-browser"]) == 1
    assert "no take.json here" in capsys.readouterr().err
    with _Served(small_take) as server:
        busy = server.server_address[1]
        assert main(["view", str(small_take), "--port", str(busy), "--no-browser"]) == 1
    assert f"port {busy} is already in use" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["view", str(small_take), "--port", "70000"])
    assert exit_info.value.code == 2


# --------------------------------------------------------------------------- browser


def _open(browser, url: str):
    """A page on the viewer, once it says it is ready; JS errors are collected in page.errors."""
    page = browser.new_page(viewport={"width": 1280, "height": 640})
    errors = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(url)
    page.wait_for_function("window.keyshape && (window.keyshape.ready || window.keyshape.error)",
                           timeout=60_000)
    assert page.evaluate("window.keyshape.error") is None
    assert errors == []
    page.errors = errors
    return page


# Mean colour of 10x10 pixel blocks of the frame the <video> shows now.
_VIDEO_BLOCKS = """() => {
  const video = document.getElementById('video');
  const canvas = document.createElement('canvas');
  const [w, h] = [Math.floor(video.videoWidth / 10), Math.floor(video.videoHeight / 10)];
  [canvas.width, canvas.height] = [10 * w, 10 * h];
  const context = canvas.getContext('2d');
  context.drawImage(video, 0, 0);
  const data = context.getImageData(0, 0, 10 * w, 10 * h).data;
  const out = new Array(w * h * 3).fill(0);
  for (let y = 0; y < 10 * h; y++) for (let x = 0; x < 10 * w; x++) {
    const i = 4 * (y * 10 * w + x), o = 3 * (Math.floor(y / 10) * w + Math.floor(x / 10));
    for (let c = 0; c < 3; c++) out[o + c] += data[i + c] / 100;
  }
  return {width: w, height: h, blocks: out};
}"""


def _video_blocks(page) -> np.ndarray:
    """``(h, w, 3)`` block means of the frame shown by the page's video."""
    got = page.evaluate(_VIDEO_BLOCKS)
    return np.array(got["blocks"]).reshape(got["height"], got["width"], 3)


def _decoded_blocks(video: Path) -> list[np.ndarray]:
    """The same block means of every frame of ``video``, decoded with PyAV."""
    import av

    with av.open(str(video)) as container:
        frames = [f.to_ndarray(format="rgb24").astype(float) for f in container.decode(video=0)]
    h, w = frames[0].shape[0] // 10, frames[0].shape[1] // 10
    return [f[:10 * h, :10 * w].reshape(h, 10, w, 10, 3).mean(axis=(1, 3)) for f in frames]


def _quaternion_distance(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(min(np.abs(a - b).max(), np.abs(a + b).max()))  # q and -q are one rotation


def _check_frame(page, frame: int, names: list[str], csv: np.ndarray, rotations) -> None:
    """The page shows ``frame``: its influences are that CSV row, its head that rotation."""
    assert page.evaluate("keyshape.frame()") == frame
    assert page.evaluate("keyshape.paused()")
    influences = page.evaluate("keyshape.influences()")
    assert list(influences) == names
    got = np.array([influences[n] for n in names])
    assert np.abs(got - csv[frame]).max() < TOLERANCE, (frame, got, csv[frame])
    if rotations is not None:
        assert _quaternion_distance(page.evaluate("keyshape.rotation()"), rotations[frame]) < TOLERANCE


def _save_screenshot(page, name: str) -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / name
    page.screenshot(path=str(path))
    print(f"screenshot: {path}")
    return path


def test_viewer_on_the_demo(browser, demo_take, record_property):
    """Play, scrub, step: the character's morph influences are the weights.csv row of the frame
    shown, its head the .glb's rotation there, and the video shows that very frame."""
    from keyshape.targets import GAZE_NAMES

    names, csv = _csv_weights(demo_take)
    anim = read_glb_animation(demo_take / "animation.glb")
    assert list(anim.names) == [*names, *GAZE_NAMES]  # the built-in head's eyes: its gaze targets
    names, csv = list(anim.names), np.hstack([csv, anim.weights[:, len(names):]])
    info = json.loads((demo_take / "take.json").read_text())
    with _Served(demo_take) as server:
        page = _open(browser, server.url)
        assert page.evaluate("keyshape.names") == names
        assert page.evaluate("[keyshape.clock, keyshape.nFrames, keyshape.fps, keyshape.webgl]") == [
            "video", info["n_frames"], info["fps"], True]

        page.evaluate("keyshape.play()")  # plays: the clock runs on its own
        page.wait_for_function("keyshape.frame() >= 12", timeout=30_000)
        assert not page.evaluate("keyshape.paused()")
        stopped = page.evaluate("keyshape.pause()")
        assert stopped >= 12
        _check_frame(page, stopped, names, csv, anim.rotations)

        decoded = _decoded_blocks(Path(info["video"]))
        busy = int(np.argmax(csv.sum(axis=1)))  # a frame far from neutral
        for frame in (busy, 0, info["n_frames"] - 1, 233):
            assert page.evaluate(f"keyshape.seek({frame})") == frame
            _check_frame(page, frame, names, csv, anim.rotations)
            shown = _video_blocks(page)
            errors = [np.abs(shown - decoded[f]).mean() if 0 <= f < len(decoded) else np.inf
                      for f in (frame - 1, frame, frame + 1)]
            assert errors[1] <= min(errors) + 0.05, (frame, errors)  # the video shows that frame

        page.locator("#scrub").fill("300")  # the slider, as a person drags it
        page.wait_for_function("keyshape.frame() === 300 && !document.getElementById('video').seeking")
        _check_frame(page, 300, names, csv, anim.rotations)
        page.keyboard.press("ArrowRight")
        page.wait_for_function("keyshape.frame() === 301 && !document.getElementById('video').seeking")
        _check_frame(page, 301, names, csv, anim.rotations)
        panel = page.locator("#weights .weight .value").all_inner_texts()
        assert panel == [f"{v:.2f}" for v in np.float32(csv[301])]

        assert page.evaluate(f"keyshape.seek({busy})") == busy
        path = _save_screenshot(page, "viewer-demo.png")
        record_property("screenshot", str(path))
        _check_character_drawn(page, demo_take, csv)
        assert page.errors == []
        page.close()


def _check_character_drawn(page, folder: Path, csv: np.ndarray) -> None:
    """The WebGL canvas shows a character, and it moves between two different frames."""
    import matplotlib.image

    def canvas() -> np.ndarray:
        return matplotlib.image.imread(io.BytesIO(page.locator("#scene").screenshot()), format="png")

    neutral = json.loads((folder / "take.json").read_text())["neutral_frame"]
    strong = int(np.argmax(np.abs(csv - csv[neutral]).sum(axis=1)))
    page.evaluate(f"keyshape.seek({neutral})")
    page.wait_for_timeout(300)
    first = canvas()
    page.evaluate(f"keyshape.seek({strong})")
    page.wait_for_timeout(300)
    second = canvas()
    background = np.median(first.reshape(-1, first.shape[-1]), axis=0)
    lit = np.abs(first - background).max(axis=-1) > 0.1
    assert 0.02 < lit.mean() < 0.9, lit.mean()  # something is drawn, not everything
    moved = np.abs(first - second).max(axis=-1) > 0.1
    assert moved.mean() > 0.002, moved.mean()


def test_viewer_on_known_answers(browser, small_take):
    """Every frame of a small take: NaN weights are 0, and the video shows frame k (grey 12·k)."""
    names, csv = _csv_weights(small_take)
    rotations = read_glb_animation(small_take / "animation.glb").rotations
    with _Served(small_take) as server:
        page = _open(browser, server.url)
        assert page.evaluate("keyshape.clock") == "video"
        for frame in [*range(20), 3]:
            assert page.evaluate(f"keyshape.seek({frame})") == frame
            _check_frame(page, frame, names, csv, rotations)
            grey = _video_blocks(page).mean()
            assert abs(grey - 12 * frame) < 4, (frame, grey)
        assert page.evaluate("keyshape.seek(99)") == 19  # clamped to the take
        page.evaluate("keyshape.play()")
        page.wait_for_function("keyshape.paused()", timeout=10_000)  # stops at the end
        assert page.evaluate("keyshape.frame()") == 19
        page.close()


def test_viewer_without_the_video(browser, tmp_path):
    """A take whose video is gone still plays: a timer is the clock."""
    folder = _write_take(tmp_path / "take", video=False)
    names, csv = _csv_weights(folder)
    with _Served(folder) as server:
        page = _open(browser, server.url)
        assert page.evaluate("keyshape.clock") == "timer"
        assert "No source video" in page.locator("#notice").inner_text()
        page.evaluate("keyshape.play()")
        page.wait_for_function("keyshape.frame() >= 3", timeout=10_000)
        page.evaluate("keyshape.pause()")
        assert page.evaluate("keyshape.seek(6)") == 6
        _check_frame(page, 6, names, csv, None)
        assert csv[6].max() == 0  # a NaN row
        page.close()


# every row of the weights panel: its heading, the name shown, whether the label is cut, its box
_PANEL_ROWS = """() => {
  let heading = null;
  const rows = [];
  for (const item of document.querySelectorAll('#weights > li')) {
    if (item.classList.contains('region')) { heading = item.textContent; continue; }
    const label = item.querySelector('.name'), bar = item.querySelector('.bar').getBoundingClientRect();
    const box = label.getBoundingClientRect();
    rows.push({heading, name: item.dataset.name, shown: label.innerText, cut: label.scrollWidth > label.clientWidth,
               right: box.right, barLeft: bar.left, visible: box.width > 0 && box.height > 0});
  }
  return {rows, headings: [...document.querySelectorAll('#weights > li.region')].map((h) => h.textContent)};
}"""


def test_viewer_weights_panel_names_whole_and_grouped_by_region(browser, demo_take):
    """Issue 36 item 7: every name shown whole (eyeSquintLeft/Right, lower_00_mirror tell apart), a
    heading per region only (upper, lower, gaze: no heading named like a mirrored key), each mirrored
    key under its original's region, the eyeLook* rows under gaze."""
    from keyshape.targets import GAZE_NAMES

    keys = json.loads((demo_take / "keys.json").read_text())["regions"]
    region_of = {key["name"]: region for region, entry in keys.items() for key in entry["keys"]}
    with _Served(demo_take) as server:
        page = _open(browser, server.url)
        seen = page.evaluate(_PANEL_ROWS)
        page.close()
    assert seen["headings"] == ["upper", "lower", "gaze"]
    rows = seen["rows"]
    assert [r["name"] for r in rows] == [*region_of, *GAZE_NAMES]
    for row in rows:
        assert row["visible"] and row["shown"] == row["name"] and not row["cut"], row
        assert row["right"] <= row["barLeft"], row  # the name ends before its bar begins
        assert row["heading"] == region_of.get(row["name"], "gaze"), row
    assert len({r["shown"] for r in rows}) == len(rows)
    assert any(r["name"].endswith("_mirror") for r in rows)


# every key row's name and the line the panel shows under it (on a line of its own: below the name's middle)
_PANEL_DESCRIPTIONS = """() => [...document.querySelectorAll('#weights > li.weight')].map((row) => {
  const text = row.querySelector('.description'), name = row.querySelector('.name');
  const box = text ? text.getBoundingClientRect() : null;
  return {name: row.dataset.name, text: text ? text.innerText : null, title: name.title,
          visible: box !== null && box.width > 0 && box.height > 0,
          below: box !== null && box.top > name.getBoundingClientRect().top + name.offsetHeight / 2};
})"""


def test_viewer_weights_panel_says_what_each_key_is(browser, demo_take):
    """Issue 36 item 12: under every key's row the panel shows its readable line (region word and
    nearest ARKit expressions, as the report gives it); the gaze rows have none."""
    from keyshape.io.keys_json import load_keys
    from keyshape.io.track import load_track
    from keyshape.report import describe_keys

    keys = load_keys(demo_take / "keys.json")
    lines = dict(zip(keys.names, describe_keys(keys, load_track(demo_take / "track.npz"),
                                               take=(keys.neutral_take, "track.npz"))))
    with _Served(demo_take) as server:
        status, _, body = _get(server, "/api/take")
        page = _open(browser, server.url)
        rows = page.evaluate(_PANEL_DESCRIPTIONS)
        page.close()
    assert status == 200 and json.loads(body)["key_descriptions"] == lines
    assert {r["name"] for r in rows if r["text"] is not None} == set(keys.names)
    for row in rows:
        if row["name"] in lines:
            assert row["text"] == lines[row["name"]] and row["visible"] and row["below"], row
            assert row["title"].startswith(f"{row['name']}: {lines[row['name']]}"), row
        else:
            assert row["name"].startswith("eyeLook") and row["text"] is None, row
    assert any(": mouth" in lines[n] for n in keys.names if n.startswith("lower"))
