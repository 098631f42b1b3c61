"""Every error and warning keyshape raises on purpose.

The command line turns any :class:`KeyshapeError` into one clear line and exit code 1.
"""


class KeyshapeError(Exception):
    """Base class: a problem with the user's input or environment, reported as one line."""


class InputError(KeyshapeError, ValueError):
    """A file or argument is missing, unreadable or of the wrong shape."""


class UsageError(InputError):
    """A command-line argument that is wrong for the input it is given (``--neutral 999`` on a
    472-frame take): the command line reports it as argparse does, with exit code 2."""


class NoFaceError(KeyshapeError):
    """A video in which the tracker found no face at all."""


class RigError(KeyshapeError):
    """A rig that cannot drive the requested key shapes (missing targets, bad topology)."""


class WriteError(KeyshapeError, OSError):
    """A file could not be written (a full disk, a quota, a folder taken away); the message names it."""


class MissingDependencyError(KeyshapeError, ImportError):
    """An optional dependency is not installed; the message says how to install it."""

    def __init__(self, package: str, extra: str | None = None):
        hint = f'pip install "keyshape[{extra}]"' if extra else f"pip install {package}"
        super().__init__(f"{package} is required for this feature: {hint}")


class InputWarning(UserWarning):
    """An input is incomplete but usable (a video that ends before the frame count its container
    declares, a take whose video is gone); the command line prints it as one line."""


class Terminated(BaseException):
    """The process was asked to stop (SIGTERM); raised like KeyboardInterrupt, so every temporary
    file and staging folder is removed on the way out."""


class DegenerateFrameWarning(UserWarning):
    """A frame whose alignment is undefined (too few finite points); its pose is NaN."""


class ConvergenceWarning(UserWarning):
    """An iterative solver stopped before its tolerance was met."""


class RenderFallbackWarning(RuntimeWarning):
    """OpenGL (moderngl on EGL) is unavailable: the slow numpy rasteriser is used instead."""


class ConvergenceError(KeyshapeError):
    """A solve that stopped short of its tolerance where its result would be written (extreme
    smoothing): reported as one line, and no file is written."""


class NotFittedError(KeyshapeError, AttributeError):
    """An estimator used before ``fit`` (as scikit-learn's ``NotFittedError``)."""
