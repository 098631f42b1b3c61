"""The one place keyshape imports ``pxr`` (OpenUSD's Python bindings, ``pip install usd-core``)."""

from __future__ import annotations

from ..exceptions import MissingDependencyError


def pxr():
    """The pxr modules, or a MissingDependencyError with the install command."""
    try:
        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdUtils, Vt
    except ImportError:
        raise MissingDependencyError("usd-core", extra="usd") from None
    return Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdUtils, Vt
