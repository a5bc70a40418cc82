"""``rtloop report DIR [DIR ...]``: figures and one self-contained HTML page of runs (compare several)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "figures and report.html of one or more runs (compare several)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("runs", nargs="+", type=Path, metavar="DIR", help="run directories (the --out of rtloop run)")
    parser.add_argument("--out", type=Path, metavar="DIR", help="where to write (default: the first run directory)")
    parser.add_argument("--no-html", action="store_true", help="write the PNG figures only")


def run(args: argparse.Namespace) -> int:
    """Write the report; what each run says about itself (a failure, not real time) goes to stderr."""
    from rtloop.report.build import build_report  # matplotlib: only when a report is drawn

    report = build_report(args.runs, args.out, write_html=not args.no_html)  # a ReportError is bad input
    for run_ in report.runs:
        if run_.failure:
            failure = run_.failure
            print(f"rtloop report: {run_.label}: run FAILED in task {failure.get('task')} "
                  f"({failure.get('phase')}, cycle {failure.get('cycle')}): {failure.get('reason')}", file=sys.stderr)
        if run_.non_rt_tasks:
            print(f"rtloop report: {run_.label}: not real-time: {', '.join(run_.non_rt_tasks)}", file=sys.stderr)
        for problem in run_.problems:
            print(f"rtloop report: {run_.label}: {problem}", file=sys.stderr)
    print(f"{len(report.pngs)} figures in {report.pngs[0].parent}/" if report.pngs else "no figures")
    if report.html is not None:
        print(f"report: {report.html}")
    return 0
