"""``keyshape track``: landmarks, ARKit-style scores and head matrix of every frame of a video."""

from __future__ import annotations

from pathlib import Path

from ._options import add_capture_options, add_visibility_option, capture_kwargs, progress, say

DESCRIPTION = ("Track the face in every frame of VIDEO with MediaPipe's FaceLandmarker (vendored model). "
               "Writes points (pixels), fps, the 52 ARKit-style scores and the head matrix to TRACK.npz; "
               "frames without a face are NaN. MediaPipe's hand landmarker looks for hands in every frame: "
               "the landmarks a hand covers are written as hidden (visibility 0; --visibility off: none).")


def add_arguments(p) -> None:
    p.add_argument("video", type=Path, help="video file (anything PyAV opens; rotation metadata "
                                            "is honoured) or a folder of images")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="TRACK.npz")
    add_capture_options(p)
    add_visibility_option(p)


def run(args) -> None:
    from ..capture import track_to_file
    from ..capture.mediapipe import defer_unused_imports

    defer_unused_imports()  # this process tracks (a segment): MediaPipe's import without its plotting

    summary = track_to_file(args.video, args.output, progress=progress(args), **capture_kwargs(args))
    n, found = summary["n_frames"], summary["n_faces"]
    say(args, f"{args.output}: {n} frames, face in {found} ({100 * found / n:.1f} %), {summary['fps']:g} fps")
