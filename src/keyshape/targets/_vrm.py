"""Automatic targets onto a VRM avatar's standard expressions (``run --rig AVATAR.vrm --auto-targets``).

A standard VRM avatar has no ARKit shapes, only VRM's presets: five vowels (VRM 1.0 ``aa ih ou ee
oh``, VRM 0.x ``A I U E O``), blinks (``blink``, ``blinkLeft``, ``blinkRight``; 0.x ``Blink``,
``Blink_L``, ``Blink_R``), looks (``lookUp/Down/Left/Right``; 0.x ``LookUp`` ...) and emotions
(``happy angry sad relaxed surprised``; 0.x ``Joy Angry Sorrow Fun``). Each key's gains onto them
come from the tracker's ARKit scores at the key's frame less those at the neutral frame
(``d = max(s(key) − s(neutral), 0)``, MediaPipe's 52 scores):

* **vowels**, from the mouth's shape, on the keys of a region holding the mouth: the key's mouth
  features ``x`` (``open = jawOpen − mouthClose``, ``mouthFunnel``, ``mouthPucker``, the mean of
  ``mouthStretchLeft/Right``, the mean of ``mouthSmileLeft/Right``) are projected onto the five
  vowel prototypes :data:`VOWEL_PROTOTYPES` by non-negative least squares, ``v = argmin_{v ≥ 0}
  ‖P v − x‖²``, and ``v`` (one gain per vowel) is the key's column;
* **blinks**, on the keys of a region holding the eyes: ``blinkLeft ← eyeBlinkLeft``,
  ``blinkRight ← eyeBlinkRight`` when the avatar has both, else ``blink ←`` their mean;
* **looks** are not mapped from keys: like ARKit rigs' gaze targets they follow the tracker's
  scores frame by frame (the mapping's ``gaze`` entries): ``lookUp ← eyeLookUpLeft``,
  ``lookDown ← eyeLookDownLeft``, ``lookLeft ← eyeLookOutLeft`` (the left eye turning out: the
  avatar looks to its left), ``lookRight ← eyeLookOutRight``;
* **emotions are not driven**: no measurement says which keys would make a face read as happy or
  sad, and a wrong emotion on an avatar is worse than none; they (and custom expressions) stay at 0,
  for the user's ``--map`` to drive.

The prototypes are not fitted to data. Each is what the ARKit shapes' definitions (Apple's
``ARFaceAnchor.BlendShapeLocation`` documentation: ``jawOpen`` opens the jaw, ``mouthFunnel``
rounds and opens the lips, ``mouthPucker`` rounds and protrudes them closed, ``mouthStretch`` and
``mouthSmile`` pull the corners out) give to the usual articulatory description of the five
Japanese vowels that VRM's presets stand for: /a/ open jaw, lips neutral; /i/ nearly closed, lips
spread; /u/ nearly closed, lips rounded and protruded; /e/ half open, lips spread; /o/ half open,
lips rounded.
"""

from __future__ import annotations

import numpy as np

from ..containers import KeyShapes
from ._mapping import SMALLEST_GAIN, Mapping

__all__ = ["VOWEL_PROTOTYPES", "is_standard_vrm", "vowel_weights", "vrm_mapping"]

VOWELS = ("aa", "ih", "ou", "ee", "oh")
MOUTH_FEATURES = ("open", "mouthFunnel", "mouthPucker", "mouthStretch", "mouthSmile")
# (n_features, n_vowels): column j is vowel j's mouth in ARKit-score space (see the module docstring)
VOWEL_PROTOTYPES = np.array([
    #  aa    ih    ou    ee    oh
    [0.70, 0.10, 0.10, 0.35, 0.45],  # open = jawOpen - mouthClose
    [0.00, 0.00, 0.30, 0.00, 0.55],  # mouthFunnel
    [0.00, 0.00, 0.70, 0.00, 0.20],  # mouthPucker
    [0.10, 0.45, 0.00, 0.35, 0.00],  # mouthStretch (mean of the sides)
    [0.00, 0.35, 0.00, 0.15, 0.00],  # mouthSmile (mean of the sides)
])
# VRM 1.0 preset -> VRM 0.x (UniVRM) spelling, for the channels this route drives
SPELLING_0 = {"aa": "A", "ih": "I", "ou": "U", "ee": "E", "oh": "O", "blink": "Blink", "blinkLeft": "Blink_L",
              "blinkRight": "Blink_R", "lookUp": "LookUp", "lookDown": "LookDown", "lookLeft": "LookLeft",
              "lookRight": "LookRight"}
LOOK_SCORES = {"lookUp": "eyeLookUpLeft", "lookDown": "eyeLookDownLeft", "lookLeft": "eyeLookOutLeft",
               "lookRight": "eyeLookOutRight"}
MOUTH_LANDMARKS = (13, 14)  # MediaPipe's inner lips, upper and lower
EYE_LANDMARKS = (159, 145, 386, 374)  # MediaPipe's upper and lower lids, both eyes


def _spelling(names) -> dict[str, str] | None:
    """The avatar's name of each preset this route drives (VRM 1.0 or 0.x spelling), or None."""
    names = set(names)
    for table in ({p: p for p in SPELLING_0}, SPELLING_0):
        if any(table[v] in names for v in VOWELS):
            return {p: n for p, n in table.items() if n in names}
    return None


def is_standard_vrm(names) -> bool:
    """Whether rig target names are a VRM avatar's preset expressions (any vowel, in either spelling)."""
    return _spelling(names) is not None


def _score(scores: np.ndarray, names: tuple, *wanted: str) -> np.ndarray:
    """The mean over ``wanted`` of the score columns (``(..., n_scores)`` → ``(...)``); 0 for unknown names."""
    columns = [names.index(n) for n in wanted if n in names]
    if not columns:
        return np.zeros(scores.shape[:-1])
    return np.nan_to_num(scores[..., columns]).mean(axis=-1)


def mouth_features(scores, names) -> np.ndarray:
    """``(..., 5)`` :data:`MOUTH_FEATURES` from ARKit scores ``(..., n_scores)`` named ``names``."""
    scores, names = np.asarray(scores, dtype=float), tuple(str(n) for n in names)
    return np.stack([_score(scores, names, "jawOpen") - _score(scores, names, "mouthClose"),
                     _score(scores, names, "mouthFunnel"), _score(scores, names, "mouthPucker"),
                     _score(scores, names, "mouthStretchLeft", "mouthStretchRight"),
                     _score(scores, names, "mouthSmileLeft", "mouthSmileRight")], axis=-1)


def vowel_weights(features: np.ndarray) -> np.ndarray:
    """``(..., 5)`` vowel weights (``aa ih ou ee oh``) of mouth features ``(..., 5)``: NNLS onto the prototypes.

    Features below 0 (a mouth more closed than the neutral's) count as 0.
    """
    from scipy.optimize import nnls

    features = np.clip(np.asarray(features, dtype=float), 0, None)
    flat = features.reshape(-1, len(MOUTH_FEATURES))
    out = np.array([nnls(VOWEL_PROTOTYPES, x)[0] if x.any() else np.zeros(len(VOWELS)) for x in flat])
    return out.reshape(*features.shape[:-1], len(VOWELS))


def vrm_mapping(keys: KeyShapes, rig_names, scores) -> Mapping:
    """Keys → a standard VRM avatar's expressions (see the module docstring).

    Parameters
    ----------
    keys : KeyShapes
    rig_names : sequence of str
        The avatar's targets (its expression names, :func:`keyshape.io.rig.load_rig` of a ``.vrm``).
    scores : KeyScores or None
        The tracker's ARKit scores at the key frames; for keys of another take (NaN there), the
        take's scores and weights stand in (:func:`_score_changes`); None: no gains.

    Returns
    -------
    Mapping
        ``matrix (n_targets, n_keys) ≥ 0`` over ``rig_names``, the look presets on ``gaze`` channels.
    """
    names = tuple(str(n) for n in rig_names)
    spelling = _spelling(names) or {}
    gains = np.zeros((len(names), keys.n_keys))
    gaze = ()
    if scores is not None:
        score_names = tuple(str(n) for n in scores.names)
        change = _score_changes(scores)  # (n_keys, n_scores)
        mouth = _keys_of_regions(keys, MOUTH_LANDMARKS)
        eyes = _keys_of_regions(keys, EYE_LANDMARKS)
        vowels = vowel_weights(mouth_features(change, score_names))  # (n_keys, 5)
        for j, vowel in enumerate(VOWELS):
            if vowel in spelling:
                gains[names.index(spelling[vowel]), mouth] = vowels[mouth, j]
        left, right = _score(change, score_names, "eyeBlinkLeft"), _score(change, score_names, "eyeBlinkRight")
        if "blinkLeft" in spelling and "blinkRight" in spelling:
            gains[names.index(spelling["blinkLeft"]), eyes] = left[eyes]
            gains[names.index(spelling["blinkRight"]), eyes] = right[eyes]
        elif "blink" in spelling:
            gains[names.index(spelling["blink"]), eyes] = (left[eyes] + right[eyes]) / 2
        gaze = tuple((spelling[look], score, 0.0) for look, score in LOOK_SCORES.items()
                     if look in spelling and score in score_names)
    gains[gains < SMALLEST_GAIN] = 0.0
    return Mapping(gains, keys.names, names, gaze=gaze)


def _score_changes(scores) -> np.ndarray:
    """``(n_keys, n_scores)``: each key's ``max(s(key) − s(neutral), 0)``; for keys of another take (no
    scores at their frames, NaN) but a take with solved weights, the change per unit key weight that a
    least-squares fit of the take's scores on its weights gives, ``s(f) ≈ c + Σ_k w_k(f) d_k``."""
    keys, neutral = np.asarray(scores.keys, float), np.asarray(scores.neutral, float)
    change = keys - neutral[None]
    missing = ~np.isfinite(change).all(axis=1)
    if missing.any() and scores.take is not None and scores.weights is not None:
        S, W = np.asarray(scores.take, float), np.asarray(scores.weights, float)
        ok = np.isfinite(S).all(axis=1) & np.isfinite(W).all(axis=1)
        if W.shape == (len(S), len(keys)) and ok.sum() > len(keys) + 1:
            X = np.column_stack([np.ones(int(ok.sum())), W[ok]])
            change[missing] = np.linalg.lstsq(X, S[ok], rcond=None)[0][1:][missing]
    return np.clip(np.nan_to_num(change), 0, None)


def _keys_of_regions(keys: KeyShapes, landmarks) -> np.ndarray:
    """``(n_keys,)`` bool: the keys whose region holds any of ``landmarks``."""
    holding = {r for r, ids in keys.regions.items() if np.isin(np.asarray(landmarks), np.asarray(ids)).any()}
    return np.array([r in holding for r in keys.key_regions], dtype=bool)
