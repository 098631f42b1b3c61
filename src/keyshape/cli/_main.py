"""The ``keyshape`` command: one module per verb, imported only when that verb runs.

Each verb module defines ``DESCRIPTION``, ``add_arguments(parser)`` and ``run(args)`` (and may
define ``check(parser, args)`` for usage errors argparse cannot see, and ``EPILOG``). The table
:data:`VERBS` gives each verb's module and one-line help, so ``keyshape --help`` lists every verb
without importing any of them.

Exit codes: 0 success, 2 usage error (argparse's, or a :class:`~keyshape.exceptions.UsageError`:
an argument wrong for its input, an output that would overwrite an input), 1 any other error (one
line; ``--debug`` for the traceback), 130 on Ctrl-C and 143 on SIGTERM (both remove every
temporary file on the way out). Warnings meant for the user
(:class:`~keyshape.exceptions.InputWarning`) are printed as one line each.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from importlib import import_module

from .. import __version__
from ..exceptions import InputWarning, KeyshapeError, Terminated, UsageError
from ._options import formatter

DESCRIPTION = """\
Turn a video of an actor's face into animation of any blendshape character
(Chuang & Bregler, Performance Driven Facial Animation using Blendshape Interpolation).

pipeline:  track VIDEO -> keys (real frames that span the performance)
           -> solve (non-negative weights per frame) -> retarget (drive a rig, write .glb)
"""

EPILOG = """\
examples:
  keyshape demo                                   # the whole path on the embedded clip
  keyshape run take.mp4 -o out/                   # track, keys, solve, default character
  keyshape track take.mp4 -o take.npz
  keyshape keys take.npz -o keys.json --count 10
  keyshape solve take.npz keys.json -o weights.csv
  keyshape retarget weights.csv --rig hero.glb --track take.npz -o hero.glb
"""

# verb -> (module in keyshape.cli, one-line help); the stages first, in pipeline order
VERBS = {
    "track": ("track", "track the face in a video (MediaPipe, 478 landmarks)"),
    "keys": ("keys", "discover key shapes (real frames) per region"),
    "solve": ("solve", "non-negative weights of every frame on the key shapes"),
    "coverage": ("coverage", "how well a key set reaches a new take: frames out of reach, keys to add"),
    "rom": ("rom", "the range-of-motion script: the expressions to film once for a key set that carries over"),
    "retarget": ("retarget", "drive a rig with the weights and write .glb, USD, CSV or Live Link Face CSV"),
    "run": ("run", "all stages: video -> track, keys, weights, animated .glb"),
    "demo": ("demo", "run the whole path on the embedded real clip"),
    "arkit": ("arkit", "export MediaPipe's ARKit scores (and head rotation) as a Live Link Face CSV"),
    "batch": ("batch", "run many takes (files or folders) on all cores or a Ray cluster; resumable"),
    "preview": ("preview", "render the side-by-side preview video of a `keyshape run` output folder"),
    "propose": ("propose", ("propose the character's target for every key shape: new targets (.glb / OBJ "
                           "folder) or a MAP.json")),
    "report": ("report", ("write preview.mp4, the pictures and a self-contained report.html for a "
                         "`keyshape run` folder")),
    "report-k": ("report_k", "error against the number of key shapes K (pca, spread, hull, spa): CSV + PNG"),
    "sculpt": ("sculpt", ("write the sculpt kit: the character with one target per key shape, a contact "
                         "sheet, a README")),
    "view": ("view", "watch the video and the animated character in sync, in a browser"),
    "live": ("live", "a camera drives a character in real time: VMC, Unreal Live Link, the browser, a recording"),
    "blender-addon": ("blender_addon", "write keyshape's Blender add-on as an installable zip"),
}


def verb_module(verb: str):
    """The module of ``verb`` (imported now)."""
    return import_module(f".{VERBS[verb][0]}", __package__)


def build_parser(verb: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``verb``'s sub-parser gets its arguments (the others list their help line).

    With ``verb=None`` every verb's module is imported and every sub-parser is complete.
    """
    parser = argparse.ArgumentParser(prog="keyshape", description=DESCRIPTION, epilog=EPILOG,
                                     formatter_class=formatter)
    parser.add_argument("--version", action="version", version=f"keyshape {__version__}")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", help="show the full traceback on errors")
    common.add_argument("-q", "--quiet", action="store_true", help="no progress bars or summaries")
    sub = parser.add_subparsers(dest="verb", metavar="VERB", required=True)
    for name, (_, help_line) in VERBS.items():
        if verb is None or name == verb:
            module = verb_module(name)
            p = sub.add_parser(name, parents=[common], formatter_class=formatter, help=help_line,
                               description=getattr(module, "DESCRIPTION", help_line),
                               epilog=getattr(module, "EPILOG", None))
            module.add_arguments(p)
            p.set_defaults(module=module, parser=p)
        else:
            sub.add_parser(name, help=help_line, add_help=False)
    return parser


def _chosen_verb(argv: list[str]) -> str | None:
    """The verb named first in ``argv`` (None for ``--help``, ``--version`` or an unknown word)."""
    first = next((a for a in argv if not a.startswith("-")), None)
    return first if first in VERBS else None


def _blas_threads():
    """One BLAS thread unless the user chose: keyshape's linear algebra is many small K x K
    products, which threads slow down (measured 1.5-3x on 2 cores); set OPENBLAS_NUM_THREADS
    or OMP_NUM_THREADS to override."""
    import os

    if any(v in os.environ for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")):
        return contextlib.nullcontext()
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``keyshape``; returns the exit code.

    Run as the command (``argv`` None: the console script, ``python -m keyshape``) the process ends
    next, so every object is then frozen out of the garbage collector (:func:`gc.freeze`): the
    interpreter's collections at exit walk them several times over, 0.3 s once numba and scipy are
    loaded, only to free memory the system takes back anyway.
    """
    with _unbroken_output():
        code = _run(sys.argv[1:] if argv is None else list(argv))
    if argv is None:
        import gc

        gc.freeze()
    return code


def _run(argv: list[str]) -> int:
    parser = build_parser(_chosen_verb(argv) or "")
    args = parser.parse_args(argv)
    module = args.module
    if hasattr(args, "start"):  # the capture options
        from ._options import check_frame_range

        check_frame_range(args.parser, args)
    if hasattr(module, "check"):
        module.check(args.parser, args)
    try:
        with _blas_threads(), _terminate_as_interrupt(), _one_line_warnings():
            from ._paths import check_outputs

            check_outputs(args.verb, args)
            module.run(args)
    except KeyboardInterrupt:
        print("keyshape: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        print("keyshape: terminated", file=sys.stderr)
        return 143
    except UsageError as exc:
        if args.debug:
            raise
        args.parser.print_usage(sys.stderr)
        print(f"keyshape {args.verb}: error: {exc}", file=sys.stderr)
        return 2
    except KeyshapeError as exc:
        if args.debug:
            raise
        print(f"keyshape: error: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # one clear line for anything unexpected too
        if args.debug:
            raise
        print(f"keyshape: error: {exc.__class__.__name__}: {exc} (run with --debug for details)",
              file=sys.stderr)
        return 1
    return 0


class _Unbroken:
    """``stream`` (stdout or stderr) that outlives its reader: once a write finds the pipe closed
    (``keyshape batch ... | head -1``), its descriptor is pointed at the null device and the rest of
    the text is dropped, so the work goes on to its end instead of dying of BrokenPipeError."""

    def __init__(self, stream):
        self._stream = stream

    def _closed_pipe(self) -> None:
        import os

        with contextlib.suppress(OSError, ValueError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self._stream.fileno())  # the buffered text, and child processes, go there too
            os.close(devnull)

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._closed_pipe()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._closed_pipe()

    def __getattr__(self, name):
        return getattr(self._stream, name)


@contextlib.contextmanager
def _unbroken_output():
    """stdout and stderr as :class:`_Unbroken` for the block (streams without a descriptor as they are)."""
    previous = sys.stdout, sys.stderr
    wrap = [stream if _descriptor(stream) is None else _Unbroken(stream) for stream in previous]
    sys.stdout, sys.stderr = wrap
    try:
        yield
    finally:
        for stream in wrap:
            with contextlib.suppress(OSError, ValueError):
                stream.flush()
        sys.stdout, sys.stderr = previous


def _descriptor(stream) -> int | None:
    try:
        return stream.fileno()
    except (AttributeError, OSError, ValueError):  # pytest's capture, StringIO
        return None


def _terminate_as_interrupt():
    """SIGTERM raises :class:`Terminated` in the main thread, as Ctrl-C raises KeyboardInterrupt,
    so ``finally`` blocks and context managers remove temporaries (``timeout``, ``kill``, a
    scheduler stopping a job). The previous handler is restored afterwards."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return contextlib.nullcontext()

    def raise_terminated(signum, frame):
        raise Terminated()

    @contextlib.contextmanager
    def installed():
        previous = signal.signal(signal.SIGTERM, raise_terminated)
        try:
            yield
        finally:
            signal.signal(signal.SIGTERM, previous)

    return installed()


def _one_line_warnings():
    """Print :class:`InputWarning` as ``keyshape: warning: ...``, once per message."""
    import warnings

    @contextlib.contextmanager
    def shown():
        with warnings.catch_warnings():
            warnings.simplefilter("default", InputWarning)
            original = warnings.showwarning

            def show(message, category, filename, lineno, file=None, line=None):
                if issubclass(category, InputWarning):
                    print(f"keyshape: warning: {message}", file=sys.stderr, flush=True)
                else:
                    original(message, category, filename, lineno, file, line)

            warnings.showwarning = show
            yield

    return shown()
