"""The ``keyshape`` command line: :func:`main`, and one module per verb (see ``_main``)."""

from ._main import VERBS, build_parser, main

__all__ = ["main", "build_parser", "VERBS"]
