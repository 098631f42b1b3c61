"""Orchestration of the stages: a take from video to files, many takes, the sculpt kit.

* :func:`discover_keys` / :func:`solve_take` — tracks → key shapes (align, neutral, regions,
  search) and a track → weights, head poses and gaze (library level, no files);
* :func:`solve_track_file` — ``keyshape solve``: :func:`solve_take` on a track file, streamed
  chunk by chunk (a long take's landmarks are never all in memory);
* :func:`extend_keys` / :func:`coverage` — a sculpted key set on a new take: the fewest keys
  to add, and how well it reaches the take;
* :func:`run_take` / :class:`RunOptions` — ``keyshape run``: one video to a take folder;
* :func:`batch` — ``keyshape batch``: many takes, resumable, in parallel (processes or Ray);
* :func:`write_sculpt_kit` — ``keyshape sculpt``: the artist's kit of targets to sculpt;
* :class:`KeyShapeModel` — the scikit-learn style estimator over the same functions;
* :func:`stage` — one log line per stage of a run (:data:`STAGE_LOGGER`), and :func:`check_drivable`
  — whether a rig's targets are named after key shapes, before any tracking.
"""

from importlib import import_module

# Each name is imported from its module on first use, so a verb loads only the stages it runs
# (``keyshape solve`` needs _stream and _pipeline, not batch, Ray, rendering or the sculpt kit).
_LAZY = {
    **dict.fromkeys(("discover_keys", "extend_keys", "coverage", "Coverage", "solve_take", "Solved",
                     "fit_errors", "head_poses", "head_and_gaze", "arkit_scores", "key_scores"), "_pipeline"),
    **dict.fromkeys(("solve_track_file", "SolvedFile"), "_stream"),
    **dict.fromkeys(("run_take", "RunOptions", "TakeSummary", "OUTPUT_FILES", "default_character_extras",
                     "drive_gaze_targets"), "_run"),
    **dict.fromkeys(("batch", "BatchRow", "find_takes", "format_table", "is_complete", "make_runner",
                     "VIDEO_SUFFIXES", "write_summary", "SequentialRunner"), "_batch"),
    **dict.fromkeys(("RayRunner", "ray_available"), "_ray"),
    **dict.fromkeys(("write_sculpt_kit", "check_kit_folder", "sculpt_targets", "contact_sheet", "SculptKit"),
                    "_sculpt"),
    "KeyShapeModel": "_model",
    **dict.fromkeys(("stage", "STAGE_LOGGER"), "_stages"),
    **dict.fromkeys(("check_drivable",), "_drivable"),
}

__all__ = [*_LAZY]  # noqa: PLE0604 - the names come from __getattr__


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'keyshape.app' has no attribute {name!r}")


def __dir__():
    return sorted({*globals(), *_LAZY})
