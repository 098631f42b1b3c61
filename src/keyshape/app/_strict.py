"""A smoothed solve either converges or fails: no unconverged weights reach a file.

The smoothed solvers (:mod:`keyshape.decompose`) return their best point with a
:class:`~keyshape.exceptions.ConvergenceWarning` when their certificate falls short, as a library
should; extreme smoothing (``--smooth 1e6`` on a real take) can stop them far from the optimum
(a certified gap of 2.6e2 where 1e-7 was asked), and such weights are no answer. The take-level
functions of :mod:`keyshape.app` (:func:`solve_take`, :func:`solve_track_file`, and so every verb
that writes weights) solve inside :func:`converged`, which turns that warning into one
:class:`~keyshape.exceptions.ConvergenceError` line instead. The per-frame NNLS's own warning
(feasible weights, a few frames not optimal) is left a warning.
"""

from __future__ import annotations

import contextlib
import warnings

from ..exceptions import ConvergenceError, ConvergenceWarning

__all__ = ["converged"]

# the smoothed solvers' messages: "the [visibility-weighted ][smoothed ]solve stopped ..."
# (not the per-frame NNLS's "the active-set solver stopped ...")
_SMOOTHED = r"the (visibility-weighted )?(smoothed )?solve stopped"


@contextlib.contextmanager
def converged(smoothness: float):
    """Run a take's solve; a smoothed solve that stops short raises :class:`ConvergenceError`
    naming ``smoothness`` and the gap it reached (the solve's threads see the same filter)."""
    if not smoothness > 0:
        yield
        return
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=_SMOOTHED, category=ConvergenceWarning)
        try:
            yield
        except ConvergenceWarning as stop:
            raise ConvergenceError(f"the smoothed solve did not converge at smoothness {smoothness:g} "
                                   f"({stop}): a smaller smoothness (--smooth) is solved exactly") from None
