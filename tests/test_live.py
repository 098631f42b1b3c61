"""keyshape live: OSC/VMC and Live Link Face encoders against real decoders, sources that drop
instead of queueing, the causal solver on known answers, and the real clip end to end (a real
python-osc receiver, the recording, faults, the browser view)."""

from __future__ import annotations

import dataclasses
import json
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from keyshape.containers import KeyShapes
from keyshape.datasets import make_performance
from keyshape.exceptions import ConvergenceWarning, InputError, RigError
from keyshape.io.livelink import LIVELINK_NAMES, ROTATION_NAMES
from keyshape.live import (
    Controls,
    LiveFrame,
    LiveLinkSender,
    LiveSolver,
    Mailbox,
    Recorder,
    Session,
    SourceFrame,
    VmcSender,
    decode_packet,
    open_source,
    run_live,
)
from keyshape.live.livelink import PACKET_NAMES
from keyshape.live.osc import bundle, message

from conftest import write_video

IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])


def _frame(names, values, *, head=IDENTITY, eyes=None, index=0, time_s=0.0) -> LiveFrame:
    return LiveFrame(index, time_s, 0.0, tuple(names), np.asarray(values, float), np.asarray(values, float),
                     np.asarray(head, float), eyes, True, np.zeros((4, 4, 3), np.uint8))


# --------------------------------------------------------------------------- OSC and VMC


def test_osc_is_what_python_osc_decodes():
    from pythonosc.osc_bundle import OscBundle
    from pythonosc.osc_message import OscMessage

    msg = OscMessage(message("/VMC/Ext/Bone/Pos", "Head", 0.0, 1.5, -2.0, 0.0, 0.0, 0.0, 1.0))
    assert msg.address == "/VMC/Ext/Bone/Pos" and msg.params == ["Head", 0.0, 1.5, -2.0, 0.0, 0.0, 0.0, 1.0]
    assert OscMessage(message("/VMC/Ext/OK", 1)).params == [1]
    assert OscMessage(message("/a/é", "naïve")).params == ["naïve"]  # UTF-8, padded after encoding
    packet = OscBundle(bundle([message("/x", 0.25), message("/VMC/Ext/Blend/Apply")]))
    assert packet.timestamp == 0 or packet.timestamp < 1  # "immediately"
    assert [(m.address, m.params) for m in packet] == [("/x", [0.25]), ("/VMC/Ext/Blend/Apply", [])]


class _Receiver:
    """A real python-osc server on 127.0.0.1 that groups the messages of each bundle."""

    def __init__(self):
        from pythonosc.dispatcher import Dispatcher
        from pythonosc.osc_server import BlockingOSCUDPServer

        self.bundles: list[list[tuple[str, tuple]]] = []
        dispatcher = Dispatcher()
        dispatcher.set_default_handler(self._on_message)
        self.server = BlockingOSCUDPServer(("127.0.0.1", 0), dispatcher)
        self.server.socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.05},
                                       daemon=True)

    def _on_message(self, address, *args):
        if address == "/VMC/Ext/OK":  # the first element of every bundle
            self.bundles.append([])
        self.bundles[-1].append((address, args))

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.server.shutdown()
        self.server.server_close()


def test_vmc_bundle_through_a_real_receiver():
    eyes = np.array([[0.0, 0.1, 0.0, np.sqrt(0.99)], [0.0, -0.1, 0.0, np.sqrt(0.99)]])
    with _Receiver() as receiver:
        sender = VmcSender("127.0.0.1", receiver.port, names=("jawOpen", "eyeBlinkLeft"))
        sender.send(_frame(("jawOpen", "eyeBlinkLeft"), [0.25, 1.5], head=[0.0, 0.6, 0.0, 0.8], eyes=eyes,
                           time_s=2.5))
        sender.close()
        deadline = time.monotonic() + 5
        while not receiver.bundles and time.monotonic() < deadline:
            time.sleep(0.01)
    (got,) = receiver.bundles
    assert [a for a, _ in got] == ["/VMC/Ext/OK", "/VMC/Ext/T", "/VMC/Ext/Blend/Val", "/VMC/Ext/Blend/Val",
                                   "/VMC/Ext/Blend/Apply", "/VMC/Ext/Bone/Pos", "/VMC/Ext/Bone/Pos",
                                   "/VMC/Ext/Bone/Pos"]
    assert got[1][1] == (2.5,)
    assert got[2][1] == ("jawOpen", 0.25) and got[3][1] == ("eyeBlinkLeft", 1.0)  # clipped to [0, 1]
    head = got[5][1]
    assert head[0] == "Head" and head[1:4] == (0.0, 0.0, 0.0)
    np.testing.assert_allclose(head[4:], [0.0, -0.6, 0.0, 0.8], atol=1e-6)  # glTF -> Unity (x mirrored)
    assert got[6][1][0] == "LeftEye" and got[7][1][0] == "RightEye"
    np.testing.assert_allclose(got[6][1][4:], [0.0, -0.1, 0.0, np.sqrt(0.99)], atol=1e-6)


def test_udp_carries_on_without_a_receiver():
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # nothing listens there now
    sender = VmcSender("127.0.0.1", port, names=("a",))
    for i in range(20):
        sender.send(_frame(("a",), [0.5], index=i))
    sender.close()
    assert sender.sent + sender.errors == 20 and sender.sent > 0


# --------------------------------------------------------------------------- Live Link


def test_livelink_packet_names_order_and_values():
    """Decode what was sent on a real socket: the byte layout field by field, the EARFaceBlendShape
    order (JawLeft before JawRight, unlike the CSV), the values by name, the rotations."""
    from scipy.spatial.transform import Rotation

    assert sorted(PACKET_NAMES) == sorted(LIVELINK_NAMES + ROTATION_NAMES) and len(PACKET_NAMES) == 61
    assert PACKET_NAMES.index("JawLeft") == 15 and PACKET_NAMES.index("JawRight") == 16
    assert PACKET_NAMES.index("MouthLeft") == 21 and PACKET_NAMES[51:53] == ("TongueOut", "HeadYaw")
    names = ("jawOpen", "JawLeft", "eyeBlink_L", "mouthSmile_R", "browInnerUp_L", "browInnerUp_R", "upper_00")
    values = [0.5, 0.2, 1.25, 0.75, 0.2, 0.4, 0.9]
    head = Rotation.from_euler("YXZ", [0.3, -0.1, 0.05]).as_quat()
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.bind(("127.0.0.1", 0))
    receiver.settimeout(5)
    sender = LiveLinkSender("127.0.0.1", receiver.getsockname()[1], names=names, fps=30000 / 1001,
                            subject="webcam", device_id="dev-1")
    sender.send(_frame(names, values, head=head, time_s=10.0))
    data, _ = receiver.recvfrom(2048)
    receiver.close(), sender.close()

    assert data[0] == 6  # version
    assert struct.unpack_from(">i", data, 1) == (5,) and data[5:10] == b"dev-1"
    assert struct.unpack_from(">i", data, 10) == (6,) and data[14:20] == b"webcam"
    frame, subframe, num, den, count = struct.unpack_from(">ifiiB", data, 20)
    assert (num, den, count) == (30000, 1001, 61) and frame == 299 and 0.7 < subframe < 0.71  # 10 s = 299.7
    assert len(data) == 20 + 17 + 4 * 61
    packet = decode_packet(data)
    assert (packet.version, packet.device_id, packet.subject, packet.frame) == (6, "dev-1", "webcam", 299)
    got = packet.as_dict()
    expected = {"JawOpen": 0.5, "JawLeft": 0.2, "EyeBlinkLeft": 1.0, "MouthSmileRight": 0.75, "BrowInnerUp": 0.3}
    for name, value in expected.items():
        assert got[name] == pytest.approx(value, abs=1e-6), name
    others = [n for n in PACKET_NAMES[:52] if n not in expected]
    assert all(got[n] == 0.0 for n in others)
    np.testing.assert_allclose([got["HeadYaw"], got["HeadPitch"], got["HeadRoll"]], [0.3, -0.1, 0.05], atol=1e-6)
    assert got["LeftEyeYaw"] == got["RightEyePitch"] == 0.0


def test_livelink_needs_arkit_names():
    with pytest.raises(RigError, match="ARKit-named targets"):
        LiveLinkSender("127.0.0.1", 11111, names=("upper_00", "lower_03"), fps=30)


# --------------------------------------------------------------------------- sources


def test_mailbox_keeps_the_newest_and_counts_drops():
    box = Mailbox()
    for i in range(3):
        box.put(SourceFrame(i, i / 30, 0.0, np.zeros(1)))
    assert box.get().index == 2 and (box.delivered, box.dropped) == (3, 2)
    assert box.get(timeout=0.01) is None and not box.closed
    box.close("gone")
    assert box.get(timeout=0.01) is None and box.closed and box.error == "gone"


@pytest.fixture(scope="module")
def grey_clip(tmp_path_factory) -> Path:
    frames = np.repeat(np.arange(0, 250, 10, dtype=np.uint8), 32 * 48 * 3).reshape(25, 32, 48, 3)
    return write_video(tmp_path_factory.mktemp("live") / "grey.mp4", frames, fps=25)


def _drain(box, *, pause: float = 0.0) -> list:
    """``(frame, time taken)`` for every frame read from ``box`` until it closes, ``pause`` s after each."""
    got = []
    while not box.closed or box.pending:
        frame = box.get(0.5)
        if frame is not None:
            got.append((frame, time.perf_counter()))
            time.sleep(pause)
    return got


def test_a_file_plays_at_its_own_rate_and_a_slow_reader_drops(grey_clip):
    source = open_source(str(grey_clip))
    assert (source.kind, source.fps, source.size) == ("file", 25.0, (48, 32))
    box = source.start()
    began = time.perf_counter()
    got = _drain(box, pause=0.1)  # a reader at 10 frames/s: 2-3 frames in 4 are dropped, none queued
    elapsed = time.perf_counter() - began
    source.stop()
    assert 0.9 < elapsed < 2.0, elapsed  # 25 frames at 25 fps: about a second, not "as fast as it decodes"
    assert box.delivered == 25 and box.dropped == 25 - len(got) and box.dropped >= 12
    lags = [taken - frame.arrival for frame, taken in got]
    assert max(lags) < 0.1, lags  # what is taken is fresh (queued, the last would be ~1 s old)
    assert [f.index for f, _ in got] == sorted(f.index for f, _ in got)


def test_a_stream_is_held_to_its_own_clock(grey_clip):
    # a URL of a stored file decodes flat out (25 frames in ~0.04 s here); held to its presentation
    # times it plays as a camera would deliver it, so its decoding cannot starve the loop
    source = open_source("file://" + str(grey_clip))
    assert (source.kind, source.fps, source.size) == ("stream", 25.0, (48, 32))
    box = source.start()
    began = time.perf_counter()
    got = [frame for frame, _ in _drain(box)]
    elapsed = time.perf_counter() - began
    source.stop()
    assert 0.9 < elapsed < 2.0, elapsed
    assert box.delivered == 25 and [f.index for f in got] == sorted(f.index for f in got)
    assert got[-1].time - got[0].time == pytest.approx(24 / 25, abs=0.01)


def test_sources_are_named_clearly(tmp_path):
    with pytest.raises(InputError, match=r"not a camera .* a video file or a stream URL"):
        open_source(str(tmp_path / "nothing.mp4"))
    if sys.platform.startswith("linux") and not Path("/dev/video7").exists():
        with pytest.raises(InputError, match="cannot open this camera"):
            open_source("7")


# --------------------------------------------------------------------------- the causal solve


def _synthetic_keys(perf) -> KeyShapes:
    names = tuple(f"{r}_{i}" for i, r in enumerate(perf.key_regions))
    return KeyShapes(perf.neutral, perf.key_deltas, names, np.zeros(perf.n_keys, int), perf.key_regions,
                     perf.regions, stable=perf.stable)


def test_solver_is_the_per_frame_solve_then_the_filter():
    from keyshape.app import solve_take

    perf = make_performance(n_frames=60, noise=0.0, random_state=3)
    keys = _synthetic_keys(perf)
    offline = solve_take(perf.track, keys, smoothness=0.0).weights.values
    raw = LiveSolver(keys, fps=30, smoothing=None)
    live = np.array([raw.step(p).keys for p in perf.track.points])
    np.testing.assert_allclose(live, offline, atol=1e-9)
    np.testing.assert_allclose(live, perf.true_weights, atol=1e-6)
    smooth = LiveSolver(keys, fps=30, smoothing={"min_cutoff": 3.0, "beta": 0.0})
    filtered = np.array([smooth.step(p).keys for p in perf.track.points])
    assert np.abs(filtered - offline).max() > 1e-3  # it smooths ...
    jitter = lambda w: np.sqrt(np.mean(np.diff(w, 2, axis=0) ** 2))  # noqa: E731
    assert jitter(filtered) < jitter(offline)  # ... and is causal: frame 0 is frame 0's solve
    np.testing.assert_allclose(filtered[0], offline[0], atol=1e-9)


def test_neutral_recapture_hold_and_return_to_neutral():
    perf = make_performance(n_frames=40, noise=0.0, random_state=4)
    keys = _synthetic_keys(perf)
    solver = LiveSolver(keys, fps=10, smoothing=None, hold=0.2)  # hold 2 frames
    busy = int(np.argmax(perf.true_weights.sum(axis=1)))
    assert solver.step(perf.track.points[busy]).keys.sum() > 0.5
    solver.recapture_neutral()
    now = solver.step(perf.track.points[busy])
    np.testing.assert_allclose(now.keys, 0.0, atol=1e-9)  # the busy face is the new neutral
    np.testing.assert_allclose(np.abs(now.head), IDENTITY, atol=1e-9)  # and its head the rest pose
    held = [solver.step(None) for _ in range(3)]
    assert not held[0].face and held[1].keys is now.keys and held[2].keys.sum() == 0.0


# --------------------------------------------------------------------------- the real clip


@pytest.fixture(scope="module")
def clip_keys(real_track, tmp_path_factory) -> Path:
    from keyshape.app import discover_keys
    from keyshape.io import save_keys

    path = tmp_path_factory.mktemp("live-keys") / "keys.json"
    save_keys(discover_keys(real_track), path)
    return path


def _live(*args, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "keyshape", "live", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kwargs)


@pytest.mark.slow
def test_live_vmc_on_the_real_clip(demo_clip, real_track, clip_keys, tmp_path):
    """`keyshape live CLIP --keys K --vmc 127.0.0.1:PORT` into a real python-osc receiver: nearly
    every frame arrives, in real time, with values in [0, 1] and a Head bone, and the weights follow
    the offline per-frame solve of the same clip."""
    from keyshape.app import solve_take
    from keyshape.io import load_keys

    keys = load_keys(clip_keys)
    duration = real_track.n_frames / real_track.fps
    with _Receiver() as receiver:
        began = time.perf_counter()
        proc = _live(demo_clip, "--keys", clip_keys, "--vmc", f"127.0.0.1:{receiver.port}")
        out, err = proc.communicate(timeout=120)
        wall = time.perf_counter() - began
        time.sleep(0.2)
    assert proc.returncode == 0, err
    print(out.strip().splitlines()[-1], f"; wall {wall:.1f} s for a {duration:.1f} s clip")
    assert wall <= 1.3 * duration, (wall, duration)
    bundles = receiver.bundles
    assert len(bundles) >= 0.95 * real_track.n_frames, (len(bundles), out)
    live = np.full((real_track.n_frames, keys.n_keys), np.nan)
    for got in bundles:
        index = int(round(dict(got)["/VMC/Ext/T"][0] * real_track.fps))
        blend = [args for address, args in got if address == "/VMC/Ext/Blend/Val"]
        assert [name for name, _ in blend] == list(keys.names)
        values = np.array([value for _, value in blend])
        assert ((values >= 0) & (values <= 1)).all()
        heads = [args for address, args in got if address == "/VMC/Ext/Bone/Pos" and args[0] == "Head"]
        assert len(heads) == 1 and abs(np.linalg.norm(heads[0][4:]) - 1) < 1e-5
        live[index] = values
    # the live solve sees no visibility (it is scored when the recording ends): compare like with like
    unseen = dataclasses.replace(real_track, visibility=None)
    offline = solve_take(unseen, keys, smoothness=0.0).weights.values
    moving = np.nanstd(offline, axis=0) >= 0.05
    ok = np.isfinite(live).all(axis=1) & np.isfinite(offline).all(axis=1)
    corr = [np.corrcoef(live[ok, k], offline[ok, k])[0, 1] for k in np.flatnonzero(moving)]
    print(f"{moving.sum()} keys move; correlation with the offline per-frame solve: mean {np.mean(corr):.3f}, "
          f"min {np.min(corr):.3f}")
    assert moving.sum() >= 5 and np.mean(corr) >= 0.9



@pytest.mark.slow
def test_live_link_from_the_command_line(demo_clip, clip_keys, tmp_path):
    """`--map` onto ARKit names and `--livelink`: Unreal's packets arrive, one per frame, the mapped
    key's weight in JawOpen (through the map's gain), the head turning in the rotation slots."""
    from keyshape.io import load_keys

    keys = load_keys(clip_keys)
    lower = next(k for k in keys.names if k.startswith("lower"))
    (tmp_path / "map.json").write_text(json.dumps(  # with a gaze target on its own channel (--auto-targets')
        {"format": "keyshape-map", "version": 1, "gains": {lower: {"jawOpen": 0.5}, keys.names[0]: {"browInnerUp": 1.0}},
         "gaze": {"eyeLookOutLeft": {"score": "eyeLookOutLeft", "rest": 0.02}}}))
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.bind(("127.0.0.1", 0))
    receiver.settimeout(0.5)
    received = []

    def listen():
        while True:
            try:
                received.append(receiver.recvfrom(4096)[0])
            except TimeoutError:
                if proc.poll() is not None:
                    return
            except OSError:
                return

    proc = _live(demo_clip, "--keys", clip_keys, "--map", tmp_path / "map.json", "--duration", "4",
                 "--livelink", f"127.0.0.1:{receiver.getsockname()[1]}", "--subject", "actor")
    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    out, err = proc.communicate(timeout=60)
    listener.join(5)
    receiver.close()
    assert proc.returncode == 0, err
    packets = [decode_packet(data) for data in received]
    assert len(packets) >= 0.9 * 4 * 23.976, (len(packets), out)
    assert {(p.version, p.subject, p.rate, len(p.values)) for p in packets} == {(6, "actor", (24000, 1001), 61)}
    frames = [p.frame for p in packets]
    assert frames == sorted(frames) and len(set(frames)) == len(frames)
    values = np.array([p.values for p in packets])
    jaw, brow = PACKET_NAMES.index("JawOpen"), PACKET_NAMES.index("BrowInnerUp")
    assert ((values[:, :52] >= 0) & (values[:, :52] <= 1)).all() and values[:, jaw].max() <= 0.5 + 1e-6
    assert np.ptp(values[:, jaw]) > 0.01 or np.ptp(values[:, brow]) > 0.01  # the face moves
    look = PACKET_NAMES.index("EyeLookOutLeft")
    assert np.ptp(values[:, look]) > 0.01  # the gaze target follows the frame's own score
    unmapped = [i for i in range(52) if i not in (jaw, brow, look)]
    assert (values[:, unmapped] == 0).all() and np.ptp(values[:, 52]) > 0.001  # head yaw turns


@pytest.mark.slow
def test_sigterm_stops_cleanly_and_keeps_the_recording(demo_clip, clip_keys, tmp_path):
    """SIGTERM mid-session: a clean exit, and the take written (re-solvable offline)."""
    from keyshape.app import solve_take
    from keyshape.io import load_keys, load_track, load_weights_csv
    from keyshape.io.gltf import read_glb_animation

    proc = _live(demo_clip, "--keys", clip_keys, "--record", tmp_path / "rec", "--vmc", "127.0.0.1:9")
    assert proc.stdout.readline().startswith("live: file WolfgangLanger_Pexels.mp4")
    time.sleep(6)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and err.strip().endswith("keyshape: terminated"), err  # once written
    assert "stopped (SIGTERM)" in out
    folder = tmp_path / "rec"
    info = json.loads((folder / "take.json").read_text())
    assert 10 < info["n_frames"] < 472
    assert {p.name for p in folder.iterdir()} == {"track.npz", "keys.json", "weights.csv", "animation.glb",
                                                 "take.json"}  # the spool became the take
    recorded, keys = load_track(folder / "track.npz"), load_keys(folder / "keys.json")
    assert recorded.n_frames == info["n_frames"] and recorded.valid.mean() >= 0.9
    sent = load_weights_csv(folder / "weights.csv")
    with warnings.catch_warnings():  # a take cut mid-occlusion: the weighted smoother may stop short (decompose/)
        warnings.simplefilter("ignore", ConvergenceWarning)
        again = solve_take(recorded, keys)  # re-solved offline with the zero-lag smoother
    assert recorded.visibility is not None  # the hand over the mouth from frame 58 on: hidden, as offline
    hidden = np.any([recorded.hidden(ix) for ix in keys.regions.values()], axis=0)
    assert hidden[70:].mean() > 0.8  # the hand covers over 30 % of a region from about frame 70 (offline: 62-69 not)
    seen = recorded.valid & ~hidden  # (a take cut while a region is hidden has no weights at its end)
    both = seen & np.isfinite(sent.values).all(axis=1)
    assert np.isfinite(again.weights.values[seen]).all() and both.sum() > 10
    assert np.corrcoef(sent.values[both].ravel(), again.weights.values[both].ravel())[0, 1] > 0.9
    assert read_glb_animation(folder / "animation.glb").weights.shape[0] == recorded.n_frames


@pytest.mark.slow
def test_calibrate_then_live_and_the_neutral_on_a_signal(demo_clip, tmp_path):
    """--calibrate: the first seconds become the key set (recorded with the take); SIGUSR1
    re-captures the neutral mid-session."""
    from keyshape.io import load_keys, load_track

    proc = _live(demo_clip, "--calibrate", "3", "--record", tmp_path / "rec", "--duration", "6",
                 "--smoothing", "none")
    lines = [proc.stdout.readline() for _ in range(3)]
    assert lines[1].startswith("calibrating:") and lines[2].startswith("calibrated on "), lines
    time.sleep(2)
    proc.send_signal(signal.SIGUSR1)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "neutral re-captured 1x" in out, out
    keys = load_keys(tmp_path / "rec" / "keys.json")
    assert set(keys.takes) == {"calibration"} and keys.n_keys >= 4
    track = load_track(tmp_path / "rec" / "track.npz")
    calibration = int(lines[2].split()[2])  # "calibrated on N frames"
    assert track.valid[:calibration].all() and track.valid.sum() > calibration  # both phases recorded


def test_a_stream_source_drops_what_it_cannot_use(tmp_path):
    """A live source far faster than the loop (FFmpeg's lavfi test pattern at 2,000 frames/s, paced by
    its realtime filter): the loop keeps up by dropping, the latency of what it takes stays small; no
    face at all is not an error. (Unpaced, the pattern's decoding thread holds the GIL so much that
    the loop got 13-84 frames through in 2 s, at a median latency of 10-150 ms.)"""
    perf = make_performance(n_frames=10, n_landmarks=478, random_state=2)
    keys = _synthetic_keys(perf)
    source = open_source("testsrc=size=160x120:rate=2000,realtime", input_format="lavfi")  # paced, 2,000 frames/s
    summary = run_live(source, lambda k: Session([Recorder(tmp_path / "rec", k, fps=30, image_size=(160, 120))]),
                       keys=keys, duration=2.0, say=lambda _: None)
    assert summary.error is None and summary.processed > 10 and summary.faces == 0
    assert summary.dropped > summary.processed and np.percentile(summary.latency, 50) < 0.05
    with np.load(tmp_path / "rec" / "track.npz") as recorded:  # kept, though with no face it is no take
        assert len(recorded["points"]) >= summary.processed and np.isnan(recorded["points"]).all()


def test_a_source_that_fails_is_reported_and_the_recording_kept(grey_clip, tmp_path, monkeypatch):
    """A camera unplugged mid-session: one clear reason, outputs closed, the recording written."""
    from keyshape.live import FrameSource

    def unplugged(self):
        for index in range(8):
            self.mailbox.put(SourceFrame(index, index / 25, time.perf_counter(), np.zeros((32, 48, 3), np.uint8)))
            time.sleep(0.04)
        raise OSError("No such device")

    monkeypatch.setattr(FrameSource, "_play_file", unplugged)
    perf = make_performance(n_frames=10, n_landmarks=478, random_state=1)
    keys = _synthetic_keys(perf)
    closed = []

    class Probe:
        def send(self, frame):
            pass

        def close(self):
            closed.append(True)

    def setup(k):
        return Session([Probe(), Recorder(tmp_path / "rec", k, fps=25, image_size=(48, 32))])

    summary = run_live(open_source(str(grey_clip)), setup, keys=keys, controls=Controls(), say=lambda _: None)
    assert summary.error is not None and "stopped delivering frames (OSError: No such device)" in summary.error
    assert closed == [True] and summary.processed >= 1
    assert (tmp_path / "rec" / "take.json").is_file() and (tmp_path / "rec" / "track.npz").is_file()


def test_live_usage_errors(capsys):
    from keyshape.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["live", "0", "--keys", "k.json"])
    assert exit_info.value.code == 2
    assert "give at least one output" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["live", "0", "--vmc", "127.0.0.1:1"])  # neither --keys nor --calibrate
    with pytest.raises(SystemExit) as exit_info:  # a recording could not be read back above 5
        main(["live", "0", "--keys", "k.json", "--vmc", "127.0.0.1:1", "--max", "7"])
    assert exit_info.value.code == 2
    assert "--max: must be at most 5" in capsys.readouterr().err


# --------------------------------------------------------------------------- the browser


@pytest.mark.browser
@pytest.mark.slow
def test_viewer_shows_live_weights_while_a_clip_plays(browser, demo_clip, clip_keys):
    proc = _live(demo_clip, "--keys", clip_keys, "--view", "--no-browser", "--duration", "25")
    try:
        url = None
        for _ in range(5):
            match = re.search(r"viewer at (http://127\.0\.0\.1:\d+/)", proc.stdout.readline())
            if match:
                url = match.group(1)
                break
        assert url, proc.stderr.read() if proc.poll() is not None else "no viewer address printed"
        page = browser.new_page(viewport={"width": 1280, "height": 640})
        errors = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(url)
        page.wait_for_function("window.keyshape && (window.keyshape.ready || window.keyshape.error)", timeout=60_000)
        assert page.evaluate("window.keyshape.error") is None and page.evaluate("keyshape.live")
        page.wait_for_function("keyshape.frames() > 10 && keyshape.images() > 2", timeout=60_000)
        samples = []
        for _ in range(4):
            samples.append((page.evaluate("keyshape.frame()"), page.evaluate("keyshape.influences()"),
                            page.locator("#weights .weight .value").all_inner_texts()))
            page.wait_for_timeout(700)
        frames = [s[0] for s in samples]
        assert frames == sorted(frames) and frames[-1] > frames[0]  # the clip plays on
        names = page.evaluate("keyshape.names")
        values = np.array([[s[1][n] for n in names] for s in samples])
        assert np.ptp(values, axis=0).max() > 0.05  # the weights change while it plays
        assert len({tuple(s[2]) for s in samples}) > 1  # and the panel shows them
        camera = page.evaluate("""() => { const c = document.getElementById('camera');
            const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
            let sum = 0; for (let i = 0; i < d.length; i += 4) sum += d[i];
            return [c.width, c.height, sum / (d.length / 4)]; }""")
        assert camera[:2] == [640, 360] and camera[2] > 20, camera  # the camera picture, not blank
        assert page.evaluate("keyshape.webgl") and errors == []
        page.close()
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)
    assert proc.returncode == 130  # stopped by Ctrl-C, as any command is


def test_recording_keeps_the_whole_frames_when_a_signal_stops_a_write(tmp_path):
    """SIGTERM between one spool file's write and the next's leaves one file a frame ahead: the
    take is written with the frames every file holds whole."""
    from keyshape.io import load_track, load_weights_csv

    perf = make_performance(n_frames=40, n_landmarks=478)  # MediaPipe's count: the built-in character's
    keys = KeyShapes(perf.neutral, perf.key_deltas, ["a", "b", "c", "d"], perf.extreme_frames, perf.key_regions,
                     perf.regions)
    rec = Recorder(tmp_path / "rec", keys, fps=30, image_size=(64, 48))
    for t in range(4):
        face = dataclasses.make_dataclass("Face", ["points", "scores", "matrix"])(
            perf.track.points[t], np.zeros(52), np.eye(4))
        rec._write(face, np.full(keys.n_keys, 0.25))
    rec._files["points"].write(np.zeros(keys.n_landmarks * 3, np.float32).tobytes())  # a fifth frame, begun
    rec.close()
    assert load_track(tmp_path / "rec" / "track.npz").n_frames == 4
    assert len(load_weights_csv(tmp_path / "rec" / "weights.csv").values) == 4
    assert not list((tmp_path / "rec").glob(".live-spool-*"))


def test_a_maps_gaze_targets_follow_each_frames_scores():
    """MAP.json's "gaze" live: the frame's score less its rest, clipped; no face holds the last value."""
    from types import SimpleNamespace

    from keyshape.live._loop import _Gaze
    from keyshape.targets import Mapping

    mapping = Mapping(np.array([[1.0], [0.0], [0.0]]), ("k",), ("jawOpen", "eyeLookIn_L", "eyeLookUp_R"),
                      gaze=(("eyeLookIn_L", "eyeLookInLeft", 0.1), ("eyeLookUp_R", "eyeLookUpRight", 0.5)))
    gaze = _Gaze(mapping, ("_neutral", "eyeLookInLeft", "eyeLookUpRight"))
    gaze.chosen = SimpleNamespace(scores=np.array([0.0, 0.6, 0.2]))
    np.testing.assert_allclose(gaze(np.array([0.3, 0.0, 0.0])), [0.3, 0.5, 0.0])
    gaze.chosen = None  # no face
    np.testing.assert_allclose(gaze(np.array([0.0, 0.0, 0.0])), [0.0, 0.5, 0.0])
