"""``rtloop sweep APP --param pi.kp=0.1:1.0:10 --duration S``: simulate a grid of parameters, one table."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rtloop.cli.arguments import at_least_one, port_feed

HELP = "simulate an app over a grid of parameters in parallel; one table of step metrics"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Simulate an app over a grid of parameter values, in parallel, and tabulate the step "
                          "response of a signal (exit 1 when every point failed).")
    parser.add_argument("app", help="app file (TOML)")
    parser.add_argument("--param", action="append", default=[], metavar="TASK.NAME=START:STOP:COUNT",
                        help="a declared parameter and its values (START:STOP:COUNT or a,b,c); repeat for a grid")
    parser.add_argument("--duration", type=float, required=True, metavar="S", help="simulated seconds per point")
    parser.add_argument("--out", type=Path, default=Path("runs/sweep"), metavar="DIR",
                        help="where the runs (DIR/0, DIR/1, ...: numbered from 0, as wide as the count needs) and "
                             "sweep.csv go (default runs/sweep)")
    parser.add_argument("--signal", default=None, metavar="NAME",
                        help="signal whose step is measured (default: the first setpoint pair's measured signal)")
    parser.add_argument("--setpoint", default=None, metavar="NAME", help="its setpoint (default: its pair's)")
    parser.add_argument("--feed", type=port_feed, action="append", default=[], metavar="PORT=FILE.csv",
                        help="feed an input port from a CSV profile")
    parser.add_argument("--force", action="store_true", help="replace a sweep already in --out")
    parser.add_argument("--processes", type=at_least_one, default=None, metavar="N",
                        help="worker processes (default: CPUs; at most 4 per CPU)")


def run(args: argparse.Namespace) -> int:
    """The table on stdout, the time it took on stderr; 1 when every point failed."""
    from rtloop.toolbox.sweep import format_table, parse_parameter, sweep

    parameters = dict(parse_parameter(text) for text in args.param)
    result = sweep(args.app, parameters, duration_s=args.duration, out=args.out, signal=args.signal,
                   setpoint=args.setpoint, processes=args.processes, feeds=dict(args.feed), force=args.force)
    if not result.signal:
        print("no signal measured (see each point's error)")
    elif result.setpoint:
        print(f"step of {result.signal} (setpoint {result.setpoint}): its first step")
    else:
        print(f"step of {result.signal}, with no setpoint: from its first value to its last, over the whole run "
              "(give --setpoint NAME to measure the step a setpoint makes)")
    print(format_table(result))
    simulated_s = args.duration * len(result.rows)
    print(f"{len(result.rows)} simulations of {args.duration:g} s in {result.elapsed_s:.1f} s on "
          f"{result.processes} processes ({simulated_s:g} s simulated); table: {result.table}", file=sys.stderr)
    failed = [row for row in result.rows if row["error"]]
    return 1 if failed and len(failed) == len(result.rows) else 0
