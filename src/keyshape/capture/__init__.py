"""Stage 1, capture: video → :class:`~keyshape.containers.Track`.

``track_video`` decodes with PyAV (:mod:`~keyshape.capture.video`, in a background thread so
decoding overlaps inference) and tracks with MediaPipe's FaceLandmarker
(:mod:`~keyshape.capture.mediapipe`). A frame without a face becomes a NaN frame; a video with no
face at all is an error. ``track_to_file`` streams the results to disk, so memory stays flat
however long the video is. :mod:`~keyshape.capture.filters` holds the gap analysis and the One
Euro filter, :mod:`~keyshape.capture.gaze` the eye rotations from the irises.
"""

from ._track import FaceFollower, track_to_file, track_video
from .filters import GapReport, OneEuro, find_gaps, gap_report, hold_neutral, one_euro
from .gaze import Gaze, estimate_gaze
from .mediapipe import BLENDSHAPE_NAMES, MediaPipeTracker, TrackerOptions, default_model_path
from .video import VideoInfo, iter_frames, probe

__all__ = ["track_video", "track_to_file", "FaceFollower", "TrackerOptions", "MediaPipeTracker",
           "default_model_path", "BLENDSHAPE_NAMES", "probe", "iter_frames", "VideoInfo",
           "Gaze", "estimate_gaze", "GapReport", "gap_report", "find_gaps", "hold_neutral", "OneEuro", "one_euro"]
