"""Stage 1, capture: video → :class:`~keyshape.containers.Track`.

``track_video`` decodes with PyAV (:mod:`~keyshape.capture.video`, in a background thread so
decoding overlaps inference) and tracks with MediaPipe's FaceLandmarker
(:mod:`~keyshape.capture.mediapipe`). A frame without a face becomes a NaN frame; a video with no
face at all is an error. ``track_to_file`` streams the results to disk, so memory stays flat
however long the video is. :mod:`~keyshape.capture.filters` holds the gap analysis and the One
Euro filter, :mod:`~keyshape.capture.gaze` the eye rotations from the irises.
"""

from importlib import import_module

# Each name is imported from its module on first use: a verb that reads only the gap analysis
# (keyshape solve) does not load the tracker, the decoder and the spool.
_LAZY = {
    **dict.fromkeys(("track_video", "track_to_file", "FaceFollower"), "_track"),
    **dict.fromkeys(("GapReport", "gap_report", "find_gaps", "hold_neutral", "OneEuro", "one_euro"), "filters"),
    **dict.fromkeys(("Gaze", "estimate_gaze"), "gaze"),
    **dict.fromkeys(("BLENDSHAPE_NAMES", "MediaPipeTracker", "TrackerOptions", "default_model_path"), "mediapipe"),
    **dict.fromkeys(("VideoInfo", "iter_frames", "probe"), "video"),
}

__all__ = ["track_video", "track_to_file", "FaceFollower", "TrackerOptions", "MediaPipeTracker",
           "default_model_path", "BLENDSHAPE_NAMES", "probe", "iter_frames", "VideoInfo",
           "Gaze", "estimate_gaze", "GapReport", "gap_report", "find_gaps", "hold_neutral", "OneEuro", "one_euro"]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'keyshape.capture' has no attribute {name!r}")


def __dir__():
    return sorted({*globals(), *_LAZY})
