"""keyshape: performance-driven facial animation by blendshape interpolation.

Implements Chuang & Bregler, *Performance Driven Facial Animation using Blendshape
Interpolation* (Stanford CS-TR-2002-02): track a face, discover key shapes (real frames),
write every frame as a non-negative blend of them, and drive any character with the weights.

The pipeline, one subpackage per stage, one function per stage here::

    track  ->  align  ->  find_keyshapes  ->  solve_weights  ->  retarget  ->  export
    capture/   alignment/   keyshapes/      decompose/       targets/      io/
                                             (render/, report/ and viewer/ to see it; app/ runs it all)

>>> import keyshape as ks
>>> perf = ks.make_performance(n_frames=80, random_state=0)
>>> aligned, poses = ks.align(perf.track, reference=perf.neutral, stable=perf.stable)
>>> keys = ks.find_keyshapes(aligned, regions=perf.regions, n_keys=2, neutral_frame=perf.neutral_frame)
>>> ks.solve_weights(aligned, keys).values.shape
(80, 4)
>>> ks.KeyShapeModel(2, regions=perf.regions, stable=perf.stable).fit(perf.track).transform(perf.track).values.shape
(80, 4)

The stage functions are imported on first use, so ``import keyshape`` stays light.
"""

from importlib import import_module

from .containers import KeyShapes, Poses, Rig, Track, Weights, blend
from .exceptions import KeyshapeError

__version__ = "0.1.0"

_LAZY = {
    # the stage verbs, in pipeline order
    "track": ("capture", "track_video"), "track_video": ("capture", "track_video"),
    "align": ("alignment", "align"), "choose_neutral": ("alignment", "choose_neutral"),
    "find_keyshapes": ("keyshapes", "find_keyshapes"), "error_vs_k": ("keyshapes", "error_vs_k"),
    "solve_weights": ("decompose", "solve_weights"),
    "retarget": ("targets", "retarget"), "Mapping": ("targets", "Mapping"),
    "propose_targets": ("targets", "propose_targets"), "propose_mapping": ("targets", "propose_mapping"),
    "auto_targets": ("targets", "auto_targets"),
    "load_rig": ("io", "load_rig"), "export": ("io", "export"),
    "render_preview": ("render", "render_preview"), "write_take_extras": ("report", "write_take_extras"),
    # takes end to end
    "discover_keys": ("app", "discover_keys"), "solve_take": ("app", "solve_take"),
    "run_take": ("app", "run_take"), "KeyShapeModel": ("app", "KeyShapeModel"),
    "estimate_gaze": ("capture", "estimate_gaze"), "make_performance": ("datasets", "make_performance"),
}

# *_LAZY adds its keys (all str). Ruff cannot see that (PLE0604); listed literally they would be
# F822, names undefined in the module, since only __getattr__ provides them.
__all__ = ["Track", "Poses", "KeyShapes", "Weights", "Rig", "blend", "KeyshapeError", "__version__",  # noqa: PLE0604
           *_LAZY]

_SUBPACKAGES = ("capture", "alignment", "keyshapes", "decompose", "targets", "io", "render", "report", "app",
                "cli", "viewer", "schemes", "metrics", "mesh", "datasets", "defaults")


def __getattr__(name: str):
    if name in _LAZY:
        module, attribute = _LAZY[name]
        return getattr(import_module(f".{module}", __name__), attribute)
    if name in _SUBPACKAGES:
        return import_module(f".{name}", __name__)
    raise AttributeError(f"module 'keyshape' has no attribute {name!r}")


def __dir__():
    return sorted({*globals(), *_LAZY, *_SUBPACKAGES})
