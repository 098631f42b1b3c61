"""Stage 4, decompose: every frame as the neutral plus a non-negative blend of the key shapes.

* :func:`solve_weights` — a take on its key shapes, region by region (the public entry);
* :func:`solve_nnls` — per-frame bounded NNLS (Lawson & Hanson; block principal pivoting);
* :func:`solve_spacetime` — the whole take at once with zero-lag temporal smoothness (ADMM with a
  duality certificate, finished by Newton / active-set steps);
* :class:`GramTake` — a long take reduced chunk by chunk to the Gram form the solvers read, then
  solved as :func:`solve_weights` solves it (``keyshape solve`` streams a track file through it).

Private modules: ``_solve`` (the public functions and their checks), ``_gramtake``, ``_nnls`` and ``_reduced``
(batched per-frame NNLS), ``_spacetime``, ``_sequence`` and ``_activeset`` (the smoothed solve),
``_weighted`` (hidden landmarks weighted by their visibility, the smoothed weighted QP exactly in
Gram form), ``_kernels``, ``_kernels_nnls``, ``_kernels_face`` and ``_kernels_weighted`` (the
numba-compiled kernels; numba is imported only in ``_kernels``, on the first solve: importing this
package is light).
"""

from ._gramtake import GramTake
from ._solve import check_upper, solve_nnls, solve_spacetime, solve_weights

__all__ = ["solve_weights", "solve_nnls", "solve_spacetime", "check_upper", "GramTake"]
