"""The estimator twin of :func:`discover_keys` and :func:`solve_take`, in the scikit-learn manner.

Parameters go to ``__init__`` (which does no work), data to :meth:`KeyShapeModel.fit`, and what is
learned ends in ``_``. The functions are the implementation; the class only holds the key set.
"""

from __future__ import annotations

from collections.abc import Sequence

from ..containers import KeyShapes, Track, Weights
from ..defaults import (
    DEFAULT_METHOD,
    DEFAULT_MIRROR,
    DEFAULT_N_KEYS,
    DEFAULT_REGIONS,
    DEFAULT_SMOOTHNESS,
    DEFAULT_UPPER,
    MAX_ERROR,
)
from ..exceptions import NotFittedError
from ._pipeline import discover_keys, solve_take

__all__ = ["KeyShapeModel"]


class KeyShapeModel:
    """Key shapes learned from one or more takes; the weights of any take on them.

    Parameters
    ----------
    n_keys : int or "auto"
        Key shapes per region (see :func:`keyshape.find_keyshapes`).
    method : "spa", "hull" or "spread", keyword-only
    regions : region scheme name, REGIONS.json path or dict region -> (n_region_landmarks,) int, keyword-only
    neutral : int or None, keyword-only
        The neutral frame of the first take; None chooses it (:func:`keyshape.choose_neutral`).
    stable : (n_stable,) int or None, keyword-only
        Landmarks to align on (default: the scheme's stable points).
    upper : float or None, keyword-only
        Upper bound of every weight, in the search and the solve.
    smoothness : float, keyword-only
        Zero-lag temporal smoothness of :meth:`transform` (0: the paper's per-frame NNLS).
    convex : bool, keyword-only
        Also require each region's weights to sum to at most 1.
    max_error : float, keyword-only
        Target of ``n_keys="auto"``, % of the inter-ocular distance.
    mirror : bool, keyword-only
        Add each key's left-right mirror where it reaches what the keys cannot
        (:func:`keyshape.keyshapes.add_mirrors`).

    Attributes
    ----------
    keyshapes_ : KeyShapes
        The key set found by :meth:`fit`.
    n_keys_ : int
        Keys over all regions, mirrored keys included.

    Examples
    --------
    >>> from keyshape.datasets import make_performance
    >>> perf = make_performance(n_frames=80, random_state=0)
    >>> model = KeyShapeModel(4, regions=perf.regions, stable=perf.stable, smoothness=0, mirror=False)
    >>> weights = model.fit(perf.track).transform(perf.track)
    >>> weights.values.shape, model.n_keys_
    ((80, 8), 8)
    """

    def __init__(self, n_keys: int | str = DEFAULT_N_KEYS, *, method: str = DEFAULT_METHOD, regions=DEFAULT_REGIONS,
                 neutral: int | None = None, stable=None, upper: float | None = DEFAULT_UPPER,
                 smoothness: float = DEFAULT_SMOOTHNESS, convex: bool = False, max_error: float = MAX_ERROR,
                 mirror: bool = DEFAULT_MIRROR):
        self.n_keys = n_keys
        self.method = method
        self.regions = regions
        self.neutral = neutral
        self.stable = stable
        self.upper = upper
        self.smoothness = smoothness
        self.convex = convex
        self.max_error = max_error
        self.mirror = mirror

    def fit(self, tracks: Track | Sequence[Track], y=None) -> KeyShapeModel:
        """Discover the key shapes of the take(s) (:func:`keyshape.discover_keys`); returns ``self``.

        ``tracks`` are in image coordinates (the alignment is part of the fit); ``y`` is ignored.
        """
        self.keyshapes_ = discover_keys(tracks, regions=self.regions, n_keys=self.n_keys, method=self.method,
                                        neutral=self.neutral, stable=self.stable, upper=self.upper,
                                        max_error=self.max_error, mirror=self.mirror)
        self.n_keys_ = self.keyshapes_.n_keys
        return self

    def transform(self, track: Track) -> Weights:
        """Weights ``(n_frames, n_keys_)`` of ``track`` on the fitted key shapes (:func:`keyshape.solve_take`)."""
        keys = self._fitted()
        return solve_take(track, keys, smoothness=self.smoothness, upper=self.upper, convex=self.convex).weights

    def fit_transform(self, tracks: Track | Sequence[Track], y=None) -> Weights:
        """``fit(tracks)``, then the weights of the first take."""
        first = tracks if isinstance(tracks, Track) else tracks[0]
        return self.fit(tracks).transform(first)

    def inverse_transform(self, weights: Weights) -> Track:
        """The key set's shapes at ``weights`` (canonical, head removed): ``neutral + Σ w_k deltas_k``."""
        keys = self._fitted()
        return Track(keys.pose(weights.values), weights.fps, frame_index=weights.frame_index, time=weights.time)

    def _fitted(self) -> KeyShapes:
        if not hasattr(self, "keyshapes_"):
            raise NotFittedError("this KeyShapeModel is not fitted yet: call fit(tracks) first")
        return self.keyshapes_

    def __repr__(self) -> str:
        return (f"KeyShapeModel(n_keys={self.n_keys!r}, method={self.method!r}, upper={self.upper!r}, "
                f"smoothness={self.smoothness!r})")
