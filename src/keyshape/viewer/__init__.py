"""The browser viewer: a local web page that plays a take's video and its animated ``.glb`` in sync.

:func:`~keyshape.viewer.server.make_server` serves one output folder of ``keyshape run`` or
``keyshape demo``; ``static/`` holds the page (``index.html``, ``viewer.css``) and the
three.js bundle ``viewer.js`` built from ``viewer/`` at the repository root.
"""
