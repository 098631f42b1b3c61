"""keyshape: performance-driven facial animation by blendshape interpolation.

Implements Chuang & Bregler, *Performance Driven Facial Animation using Blendshape
Interpolation* (Stanford CS-TR-2002-02): track a face, discover key shapes (real frames),
write every frame as a non-negative blend of them, and drive any character with the weights.

The pipeline, one module per stage::

    capture.track_video  ->  align.align  ->  keyshapes.find_keyshapes  ->  decompose.solve_weights
        ->  retarget.retarget  ->  io.export.export        (render / report / viewer to see it)

The stage functions are imported on first use, so ``import keyshape`` stays light
(``keyshape.align`` and ``keyshape.retarget`` are the modules of those stages).
"""

from importlib import import_module

from .containers import KeyShapes, Poses, Rig, Track, Weights, blend
from .exceptions import KeyshapeError

__version__ = "0.1.0"

_LAZY = {
    "track_video": "capture", "choose_neutral": "align",
    "find_keyshapes": "keyshapes", "solve_weights": "decompose", "discover_keys": "pipeline",
    "solve_take": "pipeline", "load_rig": "rig", "Mapping": "retarget",
    "export": "io.export", "render_preview": "render", "write_take_extras": "report",
    "run_take": "workflow", "make_performance": "datasets", "estimate_gaze": "gaze",
}

# *_LAZY adds its keys (all str). Ruff cannot see that (PLE0604); listed literally they would be
# F822, names undefined in the module, since only __getattr__ provides them.
__all__ = ["Track", "Poses", "KeyShapes", "Weights", "Rig", "blend", "KeyshapeError", "__version__",  # noqa: PLE0604
           *_LAZY]


_STAGES = ("capture", "align", "keyshapes", "decompose", "retarget", "rig", "io", "render", "report",
           "pipeline", "workflow", "schemes", "filters", "gaze", "metrics", "datasets")


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    if name in _STAGES:
        return import_module(f".{name}", __name__)
    raise AttributeError(f"module 'keyshape' has no attribute {name!r}")
