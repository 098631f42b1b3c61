"""Live: a camera (or a video played as one) drives a character in real time.

* :mod:`~keyshape.live.sources` — cameras (PyAV's v4l2 / avfoundation / dshow inputs), files
  played at their own rate, streams; only the newest frame is kept, late ones are dropped;
* :mod:`~keyshape.live.solver` — the causal solve: per-frame bounded NNLS, a One Euro filter on
  the weights (bounded lag), neutral re-capture;
* :mod:`~keyshape.live.osc` and :mod:`~keyshape.live.vmc` — OSC 1.0 encoding and the VMC protocol
  (VSeeFace, VNyan, Warudo);
* :mod:`~keyshape.live.livelink` — Unreal's Live Link Face UDP packets (MetaHuman);
* :mod:`~keyshape.live.record` — the session written as a take (``--record DIR``);
* :func:`run_live` — the loop (private ``_loop``); the browser view lives in ``keyshape.viewer.live``.
"""

from ._loop import Controls, LiveSummary, Session, run_live
from .character import LiveTargets, live_targets
from .frame import LiveFrame, Output, UdpOutput, parse_address
from .livelink import LiveLinkSender, decode_packet, encode_packet
from .record import Recorder
from .solver import DEFAULT_SMOOTHING, LiveSolver
from .sources import FrameSource, Mailbox, SourceFrame, open_source
from .vmc import VMC_PORT, VmcSender, vmc_bundle

__all__ = ["run_live", "Controls", "Session", "LiveSummary", "LiveTargets", "live_targets",
           "LiveFrame", "Output", "UdpOutput", "parse_address",
           "LiveLinkSender", "encode_packet", "decode_packet", "Recorder", "LiveSolver", "DEFAULT_SMOOTHING",
           "FrameSource", "Mailbox", "SourceFrame", "open_source", "VmcSender", "vmc_bundle", "VMC_PORT"]
