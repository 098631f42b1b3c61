"""Stage 3, key shapes: choose K real frames per region that span the performance.

* :func:`find_keyshapes` — the search (``spa``, successive projection, by default; the paper's
  ``spread`` and ``hull`` on the principal components), K fixed or chosen from an error target;
* :func:`error_vs_k` — reconstruction error against K, for every method (the report's curve);
* :func:`add_mirrors` — each key's left-right mirror image, where it reaches what the set cannot.

Private modules: ``_search`` (the public function and its checks), ``_select`` (the greedy
search and its objective), ``_select_pca`` (the paper's PCA methods and the candidate pool),
``_select_exchange`` (key exchange refinement), ``_kcurve`` (error against K), ``_mirror``
(mirrored keys: :func:`add_mirrors`), ``_extend`` (a key set extended to a new take:
:func:`extend_keyshapes`, per-frame errors :func:`region_errors`).
"""

from ._extend import extend_keyshapes, region_errors
from ._kcurve import CURVE_METHODS, KCurve, error_vs_k
from ._mirror import (
    MIN_REACH,
    MIRROR_SUFFIX,
    add_mirrors,
    find_mirror_pairs,
    mirror_deltas,
    mirror_gains,
    symmetry_plane,
)
from ._search import (
    MAX_CANDIDATES,
    MAX_ERROR,
    MAX_KEYS,
    METHODS,
    KChoice,
    check_neutral_frame,
    choose_n_keys,
    find_keyshapes,
)

__all__ = ["find_keyshapes", "choose_n_keys", "KChoice", "error_vs_k", "KCurve",
           "METHODS", "CURVE_METHODS", "MAX_ERROR", "MAX_KEYS", "MAX_CANDIDATES",
           "check_neutral_frame", "add_mirrors", "mirror_gains", "mirror_deltas", "find_mirror_pairs",
           "symmetry_plane", "MIN_REACH", "MIRROR_SUFFIX", "extend_keyshapes", "region_errors"]
