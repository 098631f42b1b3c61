"""Start-up of the command line: ``keyshape --help`` (and a verb's help) against a bare ``python -c pass``.

The parser imports only the chosen verb's module (``keyshape.cli``), so help costs little more
than Python's own start. Each command runs ``--repeat`` times as a fresh process; the table gives
the median wall time and the excess over ``python -c pass`` measured in the same run.

    python benchmarks/bench_cli.py
    python benchmarks/bench_cli.py --repeat 21
    python benchmarks/bench_cli.py --tree /tmp/old/src   # also another source tree (e.g. a git worktree)
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

COMMANDS = {
    "python -c pass": [sys.executable, "-c", "pass"],
    "python -c 'import numpy'": [sys.executable, "-c", "import numpy"],
    "keyshape --help": [sys.executable, "-m", "keyshape", "--help"],
    "keyshape run --help": [sys.executable, "-m", "keyshape", "run", "--help"],
    "keyshape report-k --help": [sys.executable, "-m", "keyshape", "report-k", "--help"],
}


def wall_times(command: list[str], repeat: int, env: dict | None = None) -> list[float]:
    """Seconds of ``repeat`` fresh runs of ``command`` (output discarded)."""
    out = []
    for _ in range(repeat):
        start = time.perf_counter()
        subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True, env=env)
        out.append(time.perf_counter() - start)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=11, help="runs per command (default 11)")
    parser.add_argument("--tree", default=None, metavar="SRC",
                        help="also time `keyshape --help` from this source folder (PYTHONPATH=SRC)")
    args = parser.parse_args(argv)
    medians = {name: statistics.median(wall_times(cmd, args.repeat)) for name, cmd in COMMANDS.items()}
    if args.tree:
        env = dict(os.environ, PYTHONPATH=args.tree)
        medians[f"keyshape --help ({args.tree})"] = statistics.median(
            wall_times(COMMANDS["keyshape --help"], args.repeat, env))
    base = medians["python -c pass"]
    print(f"| command | median wall time (s, {args.repeat} runs) | beyond `python -c pass` (s) |")
    print("|---|---|---|")
    for name, seconds in medians.items():
        print(f"| `{name}` | {seconds:.3f} | {seconds - base:+.3f} |")


if __name__ == "__main__":
    main()
