"""Seeing the result: fit quality, plots, contact sheets and the HTML page of a take folder.

* :func:`write_take_extras` — the pictures, the preview video and ``report.html`` of a take folder;
* :func:`fit_quality` / :class:`FitQuality` — per-frame fit error, frames outside the keys' reach;
* :mod:`~keyshape.report.plots` — the contact sheet, weight curves and error-vs-K (matplotlib);
* :func:`describe_keys` — a readable line per key: its region word and nearest ARKit expressions;
* :func:`neutral_picture` — the picture of a neutral from a file of its own (``--neutral FILE``).
"""

from ._describe import REGION_WORDS, describe_keys
from ._fit import HULL_TOLERANCE, FitQuality, face_scale, fit_quality, gap_runs, take_numbers
from ._html import write_report
from ._neutral import neutral_picture, separate_neutral
from ._take import TakeExtras, write_take_extras, write_take_preview

__all__ = ["write_take_extras", "write_take_preview", "TakeExtras", "write_report",
           "FitQuality", "fit_quality", "face_scale", "gap_runs", "take_numbers", "HULL_TOLERANCE",
           "neutral_picture", "separate_neutral", "describe_keys", "REGION_WORDS"]
