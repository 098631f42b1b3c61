"""Orchestration of the stages: a take from video to files, many takes, the sculpt kit.

* :func:`discover_keys` / :func:`solve_take` — tracks → key shapes (align, neutral, regions,
  search) and a track → weights, head poses and gaze (library level, no files);
* :func:`extend_keys` / :func:`coverage` — a sculpted key set on a new take: the fewest keys
  to add, and how well it reaches the take;
* :func:`run_take` / :class:`RunOptions` — ``keyshape run``: one video to a take folder;
* :func:`batch` — ``keyshape batch``: many takes, resumable, in parallel (processes or Ray);
* :func:`write_sculpt_kit` — ``keyshape sculpt``: the artist's kit of targets to sculpt;
* :class:`KeyShapeModel` — the scikit-learn style estimator over the same functions.
"""

from ._batch import (
    VIDEO_SUFFIXES,
    BatchRow,
    SequentialRunner,
    batch,
    find_takes,
    format_table,
    is_complete,
    make_runner,
    write_summary,
)
from ._model import KeyShapeModel
from ._pipeline import (
    Coverage,
    Solved,
    arkit_scores,
    coverage,
    discover_keys,
    extend_keys,
    fit_errors,
    head_and_gaze,
    head_poses,
    key_scores,
    solve_take,
)
from ._ray import RayRunner, ray_available
from ._run import OUTPUT_FILES, RunOptions, TakeSummary, run_take
from ._sculpt import SculptKit, check_kit_folder, contact_sheet, sculpt_targets, write_sculpt_kit

__all__ = ["discover_keys", "extend_keys", "coverage", "Coverage",
           "solve_take", "Solved", "fit_errors", "head_poses", "head_and_gaze", "arkit_scores",
           "key_scores",
           "run_take", "RunOptions", "TakeSummary", "OUTPUT_FILES",
           "batch", "BatchRow", "find_takes", "format_table", "is_complete", "make_runner", "VIDEO_SUFFIXES",
           "write_summary", "SequentialRunner", "RayRunner", "ray_available",
           "write_sculpt_kit", "check_kit_folder", "sculpt_targets", "contact_sheet", "SculptKit",
           "KeyShapeModel"]
