"""keyshape: performance-driven facial animation by blendshape interpolation.

Implements Chuang & Bregler, *Performance Driven Facial Animation using Blendshape
Interpolation* (Stanford CS-TR-2002-02): track a face, discover key shapes (real frames),
write every frame as a non-negative blend of them, and drive any character with the weights.
"""

from .containers import KeyShapes, Poses, Rig, Track, Weights, blend
from .exceptions import KeyshapeError

__version__ = "0.1.0"

__all__ = ["Track", "Poses", "KeyShapes", "Weights", "Rig", "blend", "KeyshapeError", "__version__"]
