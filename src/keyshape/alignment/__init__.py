"""Stage 2, align: remove rigid head motion from a take (Umeyama 1991; one GPA step for the neutral).

``align(track) -> (Track in canonical space, Poses)``; ``procrustes`` is the similarity fit of
one point set onto another; ``choose_neutral`` picks the take's resting frame.
"""

from ._procrustes import align, choose_neutral, procrustes

__all__ = ["align", "choose_neutral", "procrustes"]
