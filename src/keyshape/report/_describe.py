"""Words for a key shape: the part of the face it moves and the ARKit expressions it is nearest to.

A key's name (``upper_03``, ``lower_05_mirror``) says which region it belongs to and little else.
:func:`describe_keys` gives each key a line an animator can read: a region word, the two ARKit
expressions MediaPipe scored highest at the key's frame counted from the neutral frame (the
scores' rise from the neutral; both sides of one expression count as one, ``mouthSmileLeft+Right
+0.37/+0.52``), and of the others the one that sets the frame apart from the rest of the take (its
score furthest above the take's median, in units of the score's spread over the take) when it
stands out: ``mouth and jaw: mouthSmileLeft +0.62, jawOpen +0.31; unusually mouthFunnel +0.12``.
On a take where the actor smiles throughout every mouth key rises in the smile; the unusual
expression tells them apart. Only the expressions of the key's own region count (a mouth key is
not described by the brows the actor happened to raise at that frame); gaze scores (``eyeLook*``)
never do: the gaze is not a key.

A mirrored key is its source key's shape reflected through the face's plane of symmetry, so its
scores are the source's rise with the sides swapped (``...Left`` <-> ``...Right``). A key whose
frame is not in the take's track (a key set from another take) is read at the take's frame where
its solved weight is largest, given the weights and when that reaches 0.5; else, and on a track
without scores (another tracker's landmarks), it is described by its region word alone.
"""

from __future__ import annotations

import numpy as np

from ..containers import KeyShapes, Track, Weights

__all__ = ["describe_keys", "REGION_WORDS"]

REGION_WORDS = {"upper": "brows and eyes", "lower": "mouth and jaw", "brows": "brows", "left_eye": "left eye",
                "right_eye": "right eye", "mouth": "mouth", "whole": "face"}
# the ARKit expressions (by name prefix) that can describe a key of each built-in region
_REGION_SCORES = {"upper": ("brow", "eyeBlink", "eyeSquint", "eyeWide"), "brows": ("brow",),
                  "left_eye": ("eyeBlink", "eyeSquint", "eyeWide"), "right_eye": ("eyeBlink", "eyeSquint", "eyeWide"),
                  "lower": ("jaw", "mouth", "cheek", "nose", "tongue"),
                  "mouth": ("jaw", "mouth", "cheek", "nose", "tongue")}
_SHOWN, _CLEAR = 2, 0.1  # at most this many expressions; a rise below _CLEAR is "slight"
# a score this many spreads above the take's median is unusual; the floor keeps a score that
# barely varies over the take (its spread near 0) from counting as unusual for a tiny rise
_UNUSUAL, _SPREAD_FLOOR = 1.2, 0.02
_BORROW = 0.5  # a key of another take is read at this take's frame where it weighs at least this
_UNUSUAL_RISE = 0.06  # and it must rise from the neutral by this much: a score that never varies is no news


def describe_keys(keys: KeyShapes, track: Track, *, take: str | tuple[str, ...] = "",
                  weights: Weights | None = None) -> tuple[str, ...]:
    """One readable line per key shape: its region word and its nearest ARKit expressions.

    Parameters
    ----------
    keys : KeyShapes
    track : Track
        The take; its ``blendshapes (n_frames, n_scores)`` give the expressions at the key frames.
    take : str or tuple of str, keyword-only
        The take's name(s) as ``keys.takes`` records them (the video's or the track's file name);
        a key from another take is described by its region alone, unless ``weights`` is given.
    weights : Weights, optional, keyword-only
        The take's solved key weights ``(n_frames, n_keys)``, named by the keys: a key from another
        take is described at the frame of this take where its weight is largest (when it reaches
        0.5), and its line says which frame that is.

    Returns
    -------
    tuple of n_keys str

    Examples
    --------
    >>> import numpy as np
    >>> from keyshape.containers import KeyShapes, Track
    >>> names = ("jawOpen", "mouthSmileLeft", "mouthSmileRight", "browInnerUp")
    >>> scores = np.array([[0.0, 0.0, 0.0, 0.0], [0.7, 0.0, 0.0, 0.5], [0.0, 0.4, 0.05, 0.0]])
    >>> track = Track(np.zeros((3, 4, 2)), fps=30, blendshapes=scores, blendshape_names=names)
    >>> keys = KeyShapes(np.zeros((4, 2)), np.ones((3, 4, 2)), ("lower_00", "lower_01", "lower_01_mirror"),
    ...                  np.array([1, 2, 2]), ("lower",) * 3, {"lower": np.arange(4)},
    ...                  mirror_of=("", "", "lower_01"))
    >>> for line in describe_keys(keys, track):
    ...     print(line)
    mouth and jaw: jawOpen +0.70
    mouth and jaw: mouthSmileLeft +0.40
    mouth and jaw: mouthSmileRight +0.40 (lower_01 mirrored)
    """
    found = _rises(keys, track, take, weights)
    lines = []
    for k in range(keys.n_keys):
        region = keys.key_regions[k]
        word = REGION_WORDS.get(region, region)
        terms = _terms(found[0][k], found[1][k], track.blendshape_names or (), region) if found else None
        line = f"{word}: {terms}" if terms else word
        if terms and k in found[2]:
            row, weight = found[2][k]
            line += f" (as at video frame {int(track.frame_index[row])} of this take, weight {weight:.2f})"
        if keys.mirror_of[k]:
            line += f" ({keys.mirror_of[k]} mirrored)"
        lines.append(line)
    return tuple(lines)


def _rises(keys: KeyShapes, track: Track, take, weights: Weights | None):
    """``(rises, unusual, borrowed)``: both ``(n_keys, n_scores)``, each key's scores minus the
    neutral's, and minus the take's median over the take's spread (NaN rows where the key's frame is
    not in this track and no frame of it weighs the key enough); ``borrowed`` ``{key: (frame, weight)}``
    the keys of another take read at this take's frame. None without scores."""
    if track.blendshapes is None or not track.blendshape_names:
        return None
    scores = np.asarray(track.blendshapes, dtype=float)
    ours = {"", *((take,) if isinstance(take, str) else take)}
    neutral = _row(scores, track, int(keys.neutral_frame), keys.neutral_take in ours)
    if not np.isfinite(neutral).all():  # a neutral from elsewhere: the take's least score as its rest
        neutral = np.nanmin(scores, axis=0) if np.isfinite(scores).any() else neutral
    rows = np.vstack([_row(scores, track, int(f), t in ours) for f, t in zip(keys.frames, keys.takes)])
    borrowed = _borrowed(keys, weights, ~np.isfinite(rows).all(axis=1), track.n_frames)
    for k, (frame, _) in borrowed.items():
        rows[k] = scores[frame]
    seen = np.isfinite(scores).all(axis=1)
    median, spread = (np.median(scores[seen], axis=0), scores[seen].std(axis=0)) if seen.any() else (neutral, 0.0)
    rises, unusual = rows - neutral, (rows - median) / (spread + _SPREAD_FLOOR)
    names = tuple(track.blendshape_names)
    swap = [names.index(_other_side(n)) if _other_side(n) in names else i for i, n in enumerate(names)]
    for k, source in enumerate(keys.mirror_of):
        if source:  # the source key's, sides swapped
            rises[k], unusual[k] = rises[keys.names.index(source)][swap], unusual[keys.names.index(source)][swap]
            borrowed.pop(k, None)
    return rises, unusual, borrowed


def _borrowed(keys: KeyShapes, weights: Weights | None, lacking: np.ndarray, n_frames: int) -> dict:
    """``{key: (frame, weight)}``: for each key ``lacking`` its frame (not a mirror), this take's
    frame where its weight is largest, when that reaches ``_BORROW``."""
    if weights is None or weights.n_frames != n_frames:
        return {}
    found = {}
    for k in np.flatnonzero(lacking):
        if keys.mirror_of[k] or keys.names[k] not in weights.names:
            continue
        column = np.nan_to_num(np.asarray(weights.values[:, weights.names.index(keys.names[k])], dtype=float),
                               nan=-1.0)
        frame = int(np.argmax(column)) if len(column) else -1
        if frame >= 0 and column[frame] >= _BORROW:
            found[int(k)] = (frame, float(column[frame]))
    return found


def _row(scores: np.ndarray, track: Track, frame: int, own: bool) -> np.ndarray:
    if own and 0 <= frame < track.n_frames:
        return scores[frame]
    return np.full(scores.shape[1], np.nan)


def _terms(rise: np.ndarray, unusual: np.ndarray, names, region: str) -> str:
    """The strongest rises among the region's expressions, ``name +0.62``, and the most unusual of
    the others when it stands out; "" when none is known."""
    prefixes = _REGION_SCORES.get(region)
    allowed = [i for i, n in enumerate(names) if not n.startswith(("_", "eyeLook"))
               and (prefixes is None or n.startswith(prefixes)) and np.isfinite(rise[i])]
    if not allowed:
        return ""
    order = sorted(allowed, key=lambda i: -rise[i])
    terms, clear = [], set()
    for i in order:
        if len(terms) == _SHOWN or rise[i] < _CLEAR:
            break
        if i in clear:
            continue
        other = names.index(_other_side(names[i])) if _other_side(names[i]) in names else i
        if other != i and other in allowed and rise[other] >= _CLEAR:  # both sides: one term
            left, right = (i, other) if names[i].endswith("Left") else (other, i)
            terms.append(f"{names[left]}+Right {rise[left]:+.2f}/{rise[right]:+.2f}")
            clear.update((left, right))
        else:
            terms.append(f"{names[i]} {rise[i]:+.2f}")
            clear.add(i)
    if terms:
        text = ", ".join(terms)
    elif rise[order[0]] > 0.01:
        text = f"slight {names[order[0]]} {rise[order[0]]:+.2f}"
        clear.add(order[0])
    else:
        text = "close to the neutral (no expression score rises)"
    others = [i for i in allowed if i not in clear]
    odd = max(others, key=lambda i: unusual[i]) if others else None
    if odd is not None and unusual[odd] >= _UNUSUAL and rise[odd] >= _UNUSUAL_RISE:
        text += f"; unusually {names[odd]} {rise[odd]:+.2f}"
    return text


def _other_side(name: str) -> str:
    """ARKit's ``...Left`` <-> ``...Right``; other names are their own."""
    for side, other in (("Left", "Right"), ("Right", "Left")):
        if name.endswith(side):
            return name[: -len(side)] + other
    return name
