"""``keyshape live``: a camera (or a video played as one) drives a character in real time."""

from __future__ import annotations

import sys
from pathlib import Path

from ._argtypes import address, positive, tcp_port, weight_bound
from ._options import add_correspondence_option, add_visibility_option

DESCRIPTION = """\
Track a camera live and send every frame's weights, as they are solved, to any mix of
outputs: a VMC receiver (VSeeFace, VNyan, Warudo: OSC over UDP), Unreal's Live Link (the
Live Link Face app's UDP packets, for MetaHuman and ARKit-named rigs), the browser viewer
(camera and character side by side, on 127.0.0.1), and a recording of the take.

SOURCE is a camera (0, /dev/video0), a video file (played at its own frame rate, as a camera
would deliver it) or a stream URL PyAV opens (held to its own clock too). Frames the machine
cannot keep up with are dropped, never queued: the lag does not grow; drops are reported at the
end.

Keys come from a previous take (--keys) or a range-of-motion calibration of the first seconds
(--calibrate). Re-capture the neutral at any time: press n then Enter in the terminal, or send
SIGUSR1 (kill -USR1 PID). Stop with Ctrl-C or SIGTERM (or q then Enter): outputs are closed
and the recording is written."""

EPILOG = """\
examples:
  keyshape live 0 --keys keys.json --vmc 127.0.0.1:39539          # webcam -> VSeeFace
  keyshape live 0 --keys keys.json --rig arkit_head.glb --auto-targets --livelink 127.0.0.1:11111
  keyshape live 0 --calibrate 20 --view --record session/         # ROM first, then live
  keyshape live take.mp4 --keys keys.json --vmc 127.0.0.1:39539   # a file played as a camera
"""


def _smoothing(text: str):
    import argparse

    if text == "none":
        return None
    try:
        min_cutoff, beta = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be MINCUT,BETA such as 3,1 or 'none'; got {text!r}") from None
    if not min_cutoff > 0 or beta < 0:
        raise argparse.ArgumentTypeError(f"needs MINCUT > 0 and BETA >= 0; got {text!r}")
    return {"min_cutoff": min_cutoff, "beta": beta}


def _size(text: str) -> tuple[int, int]:
    import argparse

    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be WIDTHxHEIGHT such as 640x360; got {text!r}") from None
    return width, height


def add_arguments(p) -> None:
    from ..defaults import DEFAULT_UPPER

    p.add_argument("source", metavar="SOURCE", help="camera (0, /dev/video0), video file, or stream URL")
    keys = p.add_mutually_exclusive_group(required=True)
    keys.add_argument("--keys", type=Path, default=None, metavar="KEYS.json",
                      help="the key set (from `keyshape run`, `keyshape keys` or an earlier --record)")
    keys.add_argument("--calibrate", type=positive, default=None, metavar="SECONDS",
                      help="discover the keys from the first SECONDS (make every expression), then go live")
    p.add_argument("--rig", type=Path, default=None,
                   help="character whose targets to drive (.glb, .vrm, OBJ folder, USD)")
    p.add_argument("--map", type=Path, default=None, metavar="MAP.json", help="key -> target gains")
    p.add_argument("--auto-targets", action="store_true",
                   help="with --rig: propose a key -> target mapping for a rig with its own blendshapes")
    add_correspondence_option(p, when="with --auto-targets: ")
    out = p.add_argument_group("outputs (any combination, at least one)")
    out.add_argument("--vmc", type=address, default=None, metavar="HOST:PORT",
                     help="VMC protocol receiver (VSeeFace, VNyan, Warudo listen on 39539)")
    out.add_argument("--livelink", type=address, default=None, metavar="HOST:PORT",
                     help="Unreal Live Link Face receiver (port 11111); needs ARKit-named targets")
    out.add_argument("--subject", default="keyshape", help="Live Link subject name (default keyshape)")
    out.add_argument("--view", action="store_true", help="show camera and character in the browser")
    out.add_argument("--port", type=tcp_port, default=0, metavar="N", help="--view: TCP port (default: any free one)")
    out.add_argument("--no-browser", action="store_true", help="--view: only print the address")
    out.add_argument("--record", type=Path, default=None, metavar="DIR",
                     help="write the take to DIR at the end: track.npz, keys.json, weights.csv, animation.glb")
    p.add_argument("--smoothing", type=_smoothing, default=None, metavar="MINCUT,BETA",
                   help="One Euro filter on the weights (default 3,0.3: at most 53 ms of lag, 0.7 frames "
                        "measured), or 'none'")
    p.add_argument("--max", type=weight_bound, default=DEFAULT_UPPER, metavar="U",
                   help=f"upper bound of every weight, at most 5 (default {DEFAULT_UPPER:g}; 'none' lifts it to 5, "
                        f"the largest weight a recorded weights file holds)")
    p.add_argument("--face", type=int, default=0, metavar="N", help="which person to follow (0 = the largest)")
    p.add_argument("--size", type=_size, default=None, metavar="WxH", help="camera: ask for this frame size")
    p.add_argument("--camera-fps", type=positive, default=None, metavar="FPS",
                   help="camera: ask for this rate; file: play it at this rate instead of its own")
    p.add_argument("--input-format", default=None, metavar="FMT",
                   help="PyAV/FFmpeg input format for SOURCE (v4l2, avfoundation, dshow, lavfi, ...)")
    p.add_argument("--duration", type=positive, default=None, metavar="SECONDS", help="stop after SECONDS")
    add_visibility_option(p)  # in the --record take: the hands looked for in each frame (12-15 ms a frame)


def check(parser, args) -> None:
    if not (args.vmc or args.livelink or args.view or args.record):
        parser.error("give at least one output: --vmc HOST:PORT, --livelink HOST:PORT, --view or --record DIR")
    if args.auto_targets and args.rig is None:
        parser.error("--auto-targets needs --rig")
    if not args.auto_targets and (args.correspondence or args.front != "auto"):
        parser.error("--correspondence and --front only apply with --auto-targets")


def run(args) -> None:
    from ..io import load_keys
    from ..live import Controls, open_source, run_live
    from ._options import say

    keys = load_keys(args.keys) if args.keys is not None else None
    source = open_source(args.source, size=args.size, fps=args.camera_fps, input_format=args.input_format)
    controls = Controls()
    say(args, f"live: {source.kind} {source.name}, {source.size[0]}x{source.size[1]} at {source.fps:g} fps; "
              "n + Enter (or SIGUSR1) re-captures the neutral, Ctrl-C stops")
    senders = []  # the UDP outputs, to say what reached them
    with _listening(controls):
        summary = run_live(source, lambda k: _session(args, source, k, senders), keys=keys, calibrate=args.calibrate,
                           upper=args.max, smoothing=_smoothing_of(args), face=args.face, controls=controls,
                           duration=args.duration, say=lambda text: say(args, text))
    say(args, _describe(summary))
    for sender in senders:
        say(args, f"live: {sender.report()}")
    if args.record is not None and summary.keys is not None:
        from ._options import shell_command

        rerun = shell_command("keyshape", "solve", args.record / "track.npz", args.record / "keys.json", "-o",
                              args.record / "weights.csv")
        say(args, f"recorded {args.record}/: re-solve offline with `{rerun}`")
    from ..exceptions import KeyshapeError

    if summary.error:
        raise KeyshapeError(summary.error)
    lost = [s for s in senders if s.errors and not s.sent]
    if lost:
        raise KeyshapeError("; ".join(f"no packet reached {s.kind} {s.target} ({s.last_error})" for s in lost))
    _exit_as_stopped(summary.ended)


def _exit_as_stopped(ended: str) -> None:
    """A session stopped by Ctrl-C or SIGTERM ends as any command stopped so (exit 130 or 143), once
    its outputs are closed and its recording written."""
    from ..exceptions import Terminated

    if ended == "stopped (Ctrl-C)":
        raise KeyboardInterrupt
    if ended == "stopped (SIGTERM)":
        raise Terminated


def _smoothing_of(args):
    from ..live import DEFAULT_SMOOTHING

    return DEFAULT_SMOOTHING if args.smoothing is None else args.smoothing


def _session(args, source, keys, senders: list):
    """The outputs, once the key set is known (the UDP ones also appended to ``senders``)."""
    from ..capture import BLENDSHAPE_NAMES
    from ..live import LiveLinkSender, Recorder, Session, VmcSender, live_targets

    targets = live_targets(keys, rig=args.rig, mapping=args.map, auto_targets=args.auto_targets,
                           correspondence=args.correspondence, front=args.front,
                           need_rig=bool(args.view or args.record))
    outputs = []
    if args.vmc:
        outputs.append(VmcSender(*args.vmc, names=targets.names))
    if args.livelink:
        outputs.append(LiveLinkSender(*args.livelink, names=targets.names,
                                      fps=source.fps, subject=args.subject))
    senders.extend(outputs)
    if args.record:
        outputs.append(Recorder(args.record, keys, fps=source.fps, image_size=source.size, rig=targets.rig,
                                mapping=None if targets.builtin else targets.mapping,
                                source=source.spec, blendshape_names=BLENDSHAPE_NAMES, builtin=targets.builtin,
                                visibility=args.visibility))
    if args.view:
        from ..viewer.live import LiveView

        view = LiveView(targets.rig, fps=source.fps, port=args.port, name=source.name,
                        key_names=keys.names if targets.builtin else None)
        print(f"viewer at {view.url}", flush=True)
        if not args.no_browser:
            from .view import _has_display

            if _has_display():
                import webbrowser

                webbrowser.open(view.url)
        outputs.append(view)
    return Session(outputs, targets.mapping)


def _listening(controls):
    """SIGUSR1 and n + Enter re-capture the neutral, q + Enter stops."""
    import contextlib
    import signal
    import threading

    @contextlib.contextmanager
    def listening():
        previous = None
        if hasattr(signal, "SIGUSR1") and threading.current_thread() is threading.main_thread():
            previous = signal.signal(signal.SIGUSR1, lambda *_: controls.neutral.set())
        if sys.stdin is not None and sys.stdin.isatty():
            threading.Thread(target=_keys, args=(controls,), daemon=True, name="keyshape-live-keys").start()
        try:
            yield
        finally:
            if previous is not None:
                signal.signal(signal.SIGUSR1, previous)

    return listening()


def _keys(controls) -> None:
    for line in sys.stdin:
        word = line.strip().lower()
        if word in ("", "n", "neutral"):
            controls.neutral.set()
            print("live: neutral re-captured from the next frame", flush=True)
        elif word in ("q", "quit", "stop"):
            controls.stop.set()
            return


def _describe(summary) -> str:
    import numpy as np

    sent = summary.processed
    share = 100 * summary.dropped / max(summary.delivered, 1)
    text = (f"live: {summary.delivered} frames from {summary.source} ({summary.fps:g} fps) in "
            f"{summary.seconds:.1f} s: {sent} solved, {summary.dropped} dropped ({share:.1f} %), "
            f"face in {100 * summary.faces / max(sent, 1):.0f} %")
    if sent:
        ms = 1000 * summary.latency
        text += (f"; latency p50 {np.percentile(ms, 50):.1f} ms, p99 {np.percentile(ms, 99):.1f} ms "
                 f"(MediaPipe p50 {1000 * np.median(summary.detect):.1f} ms)")
    if summary.neutral_captures:
        text += f"; neutral re-captured {summary.neutral_captures}x"
    return text + f"; {summary.ended}"
