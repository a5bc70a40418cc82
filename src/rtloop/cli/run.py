"""``rtloop run APP`` and ``rtloop simulate APP``: an app in real time, or lock-step offline."""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rtloop.cli.arguments import count, port_feed, positive_seconds
from rtloop.errors import AppError, NotRealTimeWarning
from rtloop.stats import DEFAULT_TRIM

if TYPE_CHECKING:
    from rtloop.record.summary import RunSummary
    from rtloop.runtime.run_view import Progress

DEFAULT_KEEP_S = 60.0  # --keep of a run without --duration
ARTIFACTS = ("summary.json", "timing.csv", "signals.csv", "run.mcap")


def _parse_host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not port.isdigit() or not 0 <= int(port) <= 65535 or (sep and not host):
        raise argparse.ArgumentTypeError(f"--foxglove {text!r}: expected PORT or HOST:PORT, e.g. 8765 or 0.0.0.0:8765")
    return host or "127.0.0.1", int(port)


def add_simulate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("app", help="app file (TOML)")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="seconds to run (run: default until Ctrl-C or SIGTERM; simulate: required)")
    parser.add_argument("--keep", type=positive_seconds, default=None, metavar="S",
                        help="keep only the last S seconds of timing.csv, signals.csv and run.mcap, plus the "
                             "cycles around every deadline miss, stale read or fault (default: "
                             f"{DEFAULT_KEEP_S:g} without --duration, everything with it)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="directory for the artifacts (one that holds a run is refused without --force)")
    parser.add_argument("--force", action="store_true",
                        help="replace the run already in --out (its files, report.html and report-figures/)")
    parser.add_argument("--feed", type=port_feed, action="append", default=[], metavar="PORT=FILE.csv",
                        help="feed an input port from a CSV profile (t_s, values...)")
    parser.add_argument("--cpu", type=int, default=None, metavar="N",
                        help="pin every task to CPU N, whatever the app file says")
    parser.add_argument("--trim", type=count, default=DEFAULT_TRIM, metavar="N",
                        help=f"cycles left out at each end of the statistics (default {DEFAULT_TRIM})")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress, no summary table")
    parser.add_argument("--foxglove", type=_parse_host_port, default=None, metavar="[HOST:]PORT",
                        help="serve signals and timing live to Foxglove (ws://, binds 127.0.0.1 unless HOST is given)")


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    add_simulate_arguments(parser)
    parser.add_argument("--require-rt", action="store_true",
                        help="refuse to start (exit 2, saying why) a run that would not be real time")
    parser.add_argument("--trace-misses", action="store_true",
                        help="record the kernel's scheduler and IRQ events on the tasks' CPUs, to name who held a "
                             "late cycle's CPU (needs tracefs; without it, one line says so and the run goes on)")


def run(args: argparse.Namespace) -> int:
    """``rtloop run`` or ``rtloop simulate`` (``args.command``): the run, then its summary table."""
    from rtloop.app.appfile import load_app
    from rtloop.app.specs import check_duration

    if args.duration is not None:  # without one, a run lasts until SIGINT or SIGTERM
        check_duration(args.duration)
    elif args.command == "simulate":
        raise AppError("rtloop simulate needs --duration S (a simulation runs as fast as it can)")
    app = load_app(args.app)
    for port, path in args.feed:
        app.feed(port, path)
    if args.cpu is not None:
        app.pin_all(args.cpu)
    if args.foxglove is not None:
        host, port = args.foxglove
        app.serve_foxglove(port, host=host, inputs=app.live_view.inputs if app.live_view else ())
    if getattr(args, "require_rt", False):
        refuse_unless_real_time(app)
    interactive = not args.quiet and sys.stderr.isatty()
    keep_s = args.keep if args.keep is not None or args.duration is not None else DEFAULT_KEEP_S
    if args.command == "run":
        # The task server's imports run beside the supervisor's and the run's set-up (runtime/task_start.py);
        # started once the app file is taken, not for a command refused before (it would import for nothing).
        from rtloop.runtime.task_start import start_server

        start_server()
        from rtloop.runtime.supervisor import run as run_app

        try:
            with warnings.catch_warnings():  # said by realtime_warnings below, on stderr, once
                warnings.simplefilter("ignore", NotRealTimeWarning)
                summary = run_app(app, args.duration, args.out, trim=args.trim, keep_s=keep_s, force=args.force,
                                  on_progress=show_progress if interactive else None,
                                  trace_misses=args.trace_misses)
        finally:
            if interactive:
                sys.stderr.write("\n")
    else:
        from rtloop.runtime.simulate import simulate

        summary = simulate(app, args.duration, args.out, trim=args.trim, keep_s=keep_s, force=args.force)
    for warning in realtime_warnings(summary):  # a warning, on stderr: `rtloop run ... | head` still shows it
        print(warning, file=sys.stderr)
    if not args.quiet:
        print(format_summary(summary, args.out))
    return 0


COMMANDS = {
    "run": ("run an app in real time and record its timing", add_run_arguments, run),
    "simulate": ("run an app lock-step offline, as fast as possible", add_simulate_arguments, run),
}


def refuse_unless_real_time(app: Any) -> None:
    """``--require-rt``: an AppError (exit 2) naming why this run would not be real time."""
    from rtloop.linux import rt

    capabilities = rt.probe()
    if not capabilities.may_use_rt:
        raise AppError(f"--require-rt: this process may not use real-time scheduling ({capabilities.rt_reason}); "
                       "run it as root (tools/as-root) or give the user an rtprio limit (docs/service.md)")
    for name, spec in app.tasks.items():
        if spec.config.policy == "other":
            raise AppError(f"--require-rt: task {name!r} has policy = \"other\", which is not real time")
        if spec.config.priority > capabilities.max_rt_priority:
            raise AppError(f"--require-rt: task {name!r} asks for priority {spec.config.priority}, but this "
                           f"process may use at most {capabilities.max_rt_priority} ({capabilities.rt_reason})")


def show_progress(progress: Progress) -> None:
    """The run's progress line on the console (rewritten in place)."""
    until = "  (Ctrl-C stops)" if progress.duration_s is None else f" / {progress.duration_s:.1f} s"
    recording = "   RECORDING STOPPED" if progress.recording_stopped else ""
    lost = f"   LOST {progress.lost} records" if progress.lost else ""
    sys.stderr.write(f"\r  {progress.elapsed_s:7.1f} s{until}   deadline misses {progress.deadline_misses}   "
                     f"latency now {progress.latency_now_ns / 1e3:7.1f} µs{recording}{lost}  ")
    sys.stderr.flush()


def realtime_warnings(summary: RunSummary) -> list[str]:
    """One line for each task of a run that did not run real-time, with the reason."""
    return [f"WARNING: task {name!r} did NOT run real-time ({task.policy}): {task.rt_reason}"
            for name, task in summary.tasks.items() if not task.rt and summary.mode == "run"]


def format_summary(summary: RunSummary, out: Path) -> str:
    """A short table of the run (its warnings go to stderr: :func:`realtime_warnings`)."""
    from rtloop.record.summary import NOT_REAL_TIME_WORDS

    lines: list[str] = []
    header = (f"{'task':<14}{'cycles':>8} {'sched':<12}{'cpu':>4}  {'latency µs p50/p99/max':<26}"
              f"{'exec µs p50/max':<18}{'misses':>7}{'overruns':>9}{'stale conn/dev':>15}")
    lines.append(f"{summary.app}: {summary.mode} for {summary.elapsed_s:.1f} s, stopped by {summary.stopped_by}")
    lines.append(header)
    for name, task in summary.tasks.items():
        t = task.timing
        latency = "/".join(_us(v) for v in (t.latency_ns.p50, t.latency_ns.p99, t.latency_ns.max))
        sched = f"{task.policy}:{task.priority}" if task.rt else task.policy
        cpu = "-" if task.cpu is None else str(task.cpu)
        if task.host_exec_ns:  # simulated: logical time took none; show what step cost on the host
            execution = "/".join(_us(task.host_exec_ns[key]) for key in ("mean", "max")) + " host"
        else:
            execution = "/".join(_us(v) for v in (t.exec_ns.p50, t.exec_ns.max))
        stale = f"{task.stale_reads}/{summary.stale_device_reads(name)}"  # connection reads / device reads
        lines.append(f"{name:<14}{t.cycles:>8} {sched:<12}{cpu:>4}  {latency:<26}{execution:<18}"
                     f"{t.deadline_misses:>7}{t.overruns:>9}{stale:>15}")
        if task.host_exec_ns:
            host = task.host_exec_ns
            lines.append(f"  {name}: host execution time (not real time) mean {_us(host['mean'])} µs, "
                         f"max {_us(host['max'])} µs")
    for name, port in summary.ports.items():
        unread = port.direction == "out" and not port.received and port.dropped
        idle = " (nobody read it: the queue filled, then dropped)" if unread else ""
        lines.append(f"port {name} ({port.direction}, {port.signal}): {port.describe()}{idle}")
    lines += [f"misses: {line}" for line in summary.misses.get("lines", [])]  # their causes (rtloop why)
    lines += [f"note: {note}" for note in summary.notes if NOT_REAL_TIME_WORDS not in note]  # on stderr
    written = [name for name in ARTIFACTS if _holds_something(out / name)]
    lines.append(f"artifacts in {out}/: {', '.join(written)}")
    return "\n".join(lines)


def _holds_something(path: Path) -> bool:
    """A file worth listing among the artifacts (an empty run.mcap, left by a full disk, is not)."""
    try:
        return path.stat().st_size > 0
    except OSError:
        return False


def _us(value_ns: float) -> str:
    return "–" if value_ns != value_ns else f"{value_ns / 1000:.1f}"  # NaN: no cycle ran

