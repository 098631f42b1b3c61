"""Stage 2, align: remove rigid head motion from a take (Umeyama 1991; one GPA step for the neutral).

``align(track) -> (Track in canonical space, Poses)``; ``procrustes`` is the similarity fit of
one point set onto another; ``choose_neutral_frame`` picks the take's resting frame (the least
activated by the tracker's scores with the whole face in view, ``_neutral``), ``choose_neutral``
the frame nearest the median shape (the check, and the rule without scores), ``explain_neutral``
how sure a choice is.
"""

from ._neutral import NeutralChoice, activation, choose_neutral_frame, explain_neutral, least_activated
from ._procrustes import align, choose_neutral, procrustes, to_canonical

__all__ = ["align", "choose_neutral", "choose_neutral_frame", "explain_neutral", "least_activated", "activation",
           "NeutralChoice", "procrustes", "to_canonical"]
