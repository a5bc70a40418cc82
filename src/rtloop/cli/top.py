"""``rtloop top [APP] [--once]``: a live view of running apps (:mod:`rtloop.toolbox.monitor` reads them,
:mod:`rtloop.cli.top_view` draws them)."""

from __future__ import annotations

import argparse

from rtloop.cli.arguments import positive_seconds

HELP = "live view of running apps: cycles, latency, misses, CPU, page faults"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("app", nargs="?", help="app name (default: every running app; exit status 2 when the APP "
                                               "named is not running)")
    parser.add_argument("--once", action="store_true",
                        help="print one frame and exit (for scripts; exit status 1 when no app is running)")
    parser.add_argument("--interval", type=positive_seconds, default=1.0, metavar="S",
                        help="seconds between refreshes (default 1)")


def run(args: argparse.Namespace) -> int:
    """Refresh until Ctrl-C; with ``--once``, one frame and 1 when no app is running.
    An APP named that is not running is bad input (exit 2) either way: a live view that
    waited for it would wait for ever on a typo."""
    from rtloop.ipc.ports import AppNotReachable, unreachable_app
    from rtloop.toolbox.monitor import Monitor, unreachable_notes

    monitor = Monitor(args.app)
    if args.app is not None and not monitor.refresh_apps():
        unreachable = unreachable_app(args.app, monitor.refused, "top")  # another user's: say whose, as port does
        if unreachable is not None:
            raise unreachable
        refuse_unknown_app(args.app)

    from rich.console import Console
    from rich.live import Live

    from rtloop.cli.top_view import frames, render

    console = Console()
    if not console.is_terminal:
        console = Console(width=max(console.width, 200))
    if args.once:
        monitor.snapshot()  # first look: starts the %CPU, cycles/s and maximum measurements
        monitor.poll_for(min(args.interval, 0.5))
        views = monitor.snapshot()
        notes = unreachable_notes(monitor.refused)
        if not views and notes:  # apps run, as another user: not "no running app"
            raise AppNotReachable("; ".join(notes))
        console.print(render(views, console.width, notes))
        return 0 if views else 1
    try:
        views = monitor.snapshot()
        with Live(render(views, console.width, unreachable_notes(monitor.refused)), console=console,
                  auto_refresh=False) as live:
            for frame in frames(monitor, args.interval, console):
                live.update(frame, refresh=True)
    except KeyboardInterrupt:
        pass
    return 0


def refuse_unknown_app(name: str) -> None:
    """An app asked for by name that is not running: bad input, naming it and those that run (as ``port`` does)."""
    from rtloop.ipc.ports import AppNotRunning
    from rtloop.text import shorten
    from rtloop.toolbox.monitor import find_apps

    running = ", ".join(sorted({registry.app for registry in find_apps()})) or "none"
    raise AppNotRunning(f"no running app named {shorten(name)}; running: {running}")
