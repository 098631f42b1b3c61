"""``keyshape batch``: many takes, on every local core (Ray) or an existing Ray cluster.

Each take is written to ``OUTDIR/<take stem>/`` as ``keyshape run`` writes it; finished takes
are skipped on a rerun when their manifest (``batch.json``: the video's fingerprint and the
options) still matches, and ``--force`` reruns them all; a failed take is reported and the
others go on. The summary table is printed and written to ``OUTDIR/summary.csv``; the exit code
is 1 if any take failed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..exceptions import KeyshapeError

DESCRIPTION = (
    "Run track -> keys -> solve -> retarget -> exports for every take, each into OUTDIR/<take stem>/. "
    "TAKES are video files and/or folders (every video directly inside). Takes already finished in "
    "OUTDIR from the same video and options are skipped (--force reruns them); a take that fails is "
    "reported and the others go on. With Ray installed "
    "(pip install \"keyshape[ray]\") the takes run in parallel on a private local Ray instance, one "
    "worker per core, or on a running cluster with --address; without Ray, or with --sequential, "
    "they run one after the other with the same outputs. Writes OUTDIR/summary.csv; exit code 1 "
    "if any take failed."
)


def _workers(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number; got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1; got {value}")
    return value


def add_arguments(p) -> None:
    from ._options import add_key_options, add_solve_options, add_visibility_option

    p.add_argument("takes", type=Path, nargs="+", metavar="TAKE",
                   help="video files and/or folders of videos")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="OUTDIR")
    p.add_argument("--rig", type=Path, default=None,
                   help="character for every take (OBJ folder, .glb/.gltf, .vrm or USD), as for `run`")
    p.add_argument("--map", type=Path, default=None, metavar="MAP.json",
                   help="key -> rig target gains (JSON), as for `run`")
    keys = p.add_mutually_exclusive_group()
    keys.add_argument("--keys", type=Path, default=None, metavar="KEYS.json",
                      help="solve every take against this key set")
    keys.add_argument("--shared-keys", action="store_true",
                      help="track every take, discover ONE key set across all of them "
                           "(OUTDIR/keys.json) and solve every take against it")
    add_key_options(p)
    add_solve_options(p)
    add_visibility_option(p)
    where = p.add_mutually_exclusive_group()
    where.add_argument("--address", default=None, metavar="HOST:PORT",
                       help="join a running Ray cluster (the address `ray start --head` prints); "
                            "TAKES and OUTDIR must be on storage every node sees at the same path")
    where.add_argument("--sequential", action="store_true",
                       help="no Ray: one take after the other in this process")
    p.add_argument("--workers", type=_workers, default=None, metavar="N",
                   help="CPUs of the local Ray instance (default: every core)")
    p.add_argument("--no-preview", action="store_true",
                   help="skip each take's preview video (the slowest extra)")
    p.add_argument("--force", action="store_true",
                   help="rerun every take (default: a take is skipped when its outputs are complete and "
                        "its manifest OUTDIR/<take>/batch.json matches its video and these options)")
    from .run import add_format_option

    add_format_option(p)


def run(args) -> None:
    from ..app import RunOptions, batch, format_table, make_runner
    from ._options import solve_kwargs

    options = RunOptions(rig=args.rig, mapping=args.map, keys=args.keys, regions=args.regions,
                         n_keys=args.count, max_error=args.max_error, method=args.method,
                         mirror=args.mirror, neutral=args.neutral, preview=not args.no_preview,
                         formats=tuple(args.formats), capture={"visibility": args.visibility},
                         **solve_kwargs(args))
    runner = make_runner(sequential=args.sequential, workers=args.workers, address=args.address)
    if not args.quiet and runner.name == "sequential" and not args.sequential:
        print("keyshape: Ray is not installed; running the takes one after the other "
              '(pip install "keyshape[ray]" to use every core)', file=sys.stderr)

    def say(row) -> None:
        if not args.quiet:
            detail = f" ({row.error})" if row.error else ""
            print(f"{row.status:>7}  {row.take}{detail}", file=sys.stderr, flush=True)

    rows = batch(args.takes, args.output, options, shared_keys=args.shared_keys, runner=runner,
                 on_row=say, force=args.force)
    if not args.quiet:
        print(format_table(rows))
        print(f"wrote {args.output / 'summary.csv'}")
    failed = [r for r in rows if r.status == "failed"]
    if failed:
        raise _BatchFailed(len(failed), len(rows))


class _BatchFailed(KeyshapeError):
    """Some takes failed: exit code 1, one line (their errors are in the table above)."""

    def __init__(self, n_failed: int, n_takes: int):
        super().__init__(f"{n_failed} of {n_takes} takes failed (see the table above and summary.csv)")
