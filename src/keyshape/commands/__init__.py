"""Extra sub-commands of ``keyshape``, one module each, found automatically.

A module here defines ``VERB`` (str), ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> None``; :mod:`keyshape.cli` adds it as ``keyshape VERB``. Keep ``run`` a thin
call into the public API.
"""

from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType


def discover() -> list[ModuleType]:
    """The command modules in this package, sorted by verb."""
    modules = [importlib.import_module(f"{__name__}.{info.name}")
               for info in pkgutil.iter_modules(__path__) if not info.name.startswith("_")]
    return sorted((m for m in modules if hasattr(m, "VERB")), key=lambda m: m.VERB)
