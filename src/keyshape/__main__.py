"""``python -m keyshape`` is the ``keyshape`` command."""

from .cli import main

raise SystemExit(main())
