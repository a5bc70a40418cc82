"""``rtloop replay RUN_DIR --out DIR``: re-simulate a run along its real timeline; compare its signals."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rtloop.cli.arguments import EXIT_FAILED

HELP = "re-simulate a run along its real timeline; compare its signals"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="output folder of `rtloop run`")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="directory for the replay's artifacts (never RUN_DIR nor inside it)")
    parser.add_argument("--force", action="store_true", help="replace the run already in --out")


def run(args: argparse.Namespace) -> int:
    """0 when the replay's signals equal the run's, bit for bit; 1 (saying where and why) when not."""
    from rtloop.runtime.replay import replay
    from rtloop.text import counted

    result = replay(args.run_dir, args.out, force=args.force)
    followed = (f"{counted(result.skipped_releases, 'skipped release')}, "
                f"{counted(result.stale_reads, 'stale connection read')} "
                f"and {counted(result.port_inputs, 'port input')} followed")
    for note in result.notes:
        print(f"note: {note}", file=sys.stderr)
    if result.equal:
        span = "the whole run" if not result.from_s else f"the kept window from t = {result.from_s:g} s to the end"
        print(f"replay of {args.run_dir}: signals equal bit for bit over {span} ({result.rows_compared} rows; "
              f"{followed}); artifacts in {args.out}/")
        return 0
    if result.divergence is not None:
        print(f"replay of {args.run_dir}: signals differ ({result.rows_compared} of {result.rows_in_run} rows equal "
              f"first; {followed})\n{result.divergence.describe()}", file=sys.stderr)
    if result.cannot is not None:
        print(f"replay of {args.run_dir}: cannot reproduce the run {result.cannot} "
              f"({result.rows_compared} rows before that equal)", file=sys.stderr)
    if result.lost:
        found = "" if result.divergence or result.cannot else (
            f"the {result.rows_compared} rows it holds are equal where it kept their values ({followed}), but ")
        print(f"replay of {args.run_dir}: {found}the run lost part of what it did, so it is not called equal:",
              file=sys.stderr)
        for line in result.lost:
            print(f"  lost: {line}", file=sys.stderr)
    return EXIT_FAILED
