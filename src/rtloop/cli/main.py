"""The ``rtloop`` command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rtloop.cli.arguments import positive_seconds
from rtloop.errors import AppError, RtloopError, TaskFailed
from rtloop.record.summary import RunSummary
from rtloop.text import clip

if TYPE_CHECKING:
    from rtloop.runtime.supervisor import Progress

EXIT_TASK_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130  # as a shell reports death by SIGINT
DEFAULT_KEEP_S = 60.0  # --keep of a run without --duration
ARTIFACTS = ("summary.json", "timing.csv", "signals.csv", "run.mcap")
# Commands with parsers of their own: `rtloop NAME ARGS...` is `python -m rtloop.MODULE ARGS...`.
DELEGATED = {
    "report": ("rtloop.report.build", "figures and report.html of one or more runs (compare several)"),
    "top": ("rtloop.cli.top", "live view of running apps: cycles, latency, misses, CPU, page faults"),
    "doctor": ("rtloop.cli.doctor", "is this machine ready for real time? how to fix what is not"),
    "bridge": ("rtloop.ros.bridge", "ROS 2 listener/talker nodes between topics and an app's ports"),
    "bench": ("rtloop.cli.bench", "the thesis's chapter-6 experiments on this machine, with a report"),
    "service": ("rtloop.cli.service", "a systemd unit that runs an app until stopped (--install writes it)"),
    "io": ("rtloop.cli.devices", "GPIO chips, CAN interfaces, spidev, serial lines, I2C buses: may you open them?"),
    "sweep": ("rtloop.cli.sweep", "simulate an app over a grid of parameters in parallel; one table of step metrics"),
}


# Optional packages and the extra that installs them (the core needs numpy only).
EXTRAS = {"mcap": "ros", "mcap_ros2": "ros", "cyclonedds": "ros", "rich": "report", "matplotlib": "report",
          "fmpy": "fmu", "foxglove": "live", "serial": "serial"}


def missing_extra(error: ModuleNotFoundError) -> str:
    """One line for a missing optional package: what is missing and what installs it."""
    top = (error.name or "").split(".")[0]
    extra = EXTRAS.get(top)
    if extra is None:
        return f"the Python package {top!r} is missing"
    return f"needs the optional package {top!r}: pip install 'rtloop[{extra}]'"


def _parse_feed(text: str) -> tuple[str, Path]:
    port, sep, path = text.partition("=")
    if not sep or not port or not path:
        raise argparse.ArgumentTypeError(f"--feed {text!r}: expected PORT=FILE.csv")
    return port, Path(path)


def _parse_host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not port.isdigit() or not 0 <= int(port) <= 65535 or (sep and not host):
        raise argparse.ArgumentTypeError(f"--foxglove {text!r}: expected PORT or HOST:PORT, e.g. 8765 or 0.0.0.0:8765")
    return host or "127.0.0.1", int(port)


def _add_run_arguments(parser: argparse.ArgumentParser) -> None:
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
    parser.add_argument("--feed", type=_parse_feed, action="append", default=[], metavar="PORT=FILE.csv",
                        help="feed an input port from a CSV profile (t_s, values...)")
    parser.add_argument("--cpu", type=int, default=None, metavar="N",
                        help="pin every task to CPU N, whatever the app file says")
    parser.add_argument("--trim", type=int, default=20, metavar="N",
                        help="cycles left out at each end of the statistics (default 20)")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress, no summary table")
    parser.add_argument("--foxglove", type=_parse_host_port, default=None, metavar="[HOST:]PORT",
                        help="serve signals and timing live to Foxglove (ws://, binds 127.0.0.1 unless HOST is given)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rtloop", description="Real-time control loops in Python on Linux.")
    parser.add_argument("--debug", action="store_true", help="show the Python traceback behind an error")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = commands.add_parser("run", help="run an app in real time and record its timing")
    _add_run_arguments(run)
    run.add_argument("--require-rt", action="store_true",
                     help="refuse to start (exit 2, saying why) a run that would not be real time")
    simulate = commands.add_parser("simulate", help="run an app lock-step offline, as fast as possible")
    _add_run_arguments(simulate)

    replay = commands.add_parser("replay", help="re-simulate a run along its real timeline; compare its signals")
    replay.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="output folder of `rtloop run`")
    replay.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="directory for the replay's artifacts (never RUN_DIR nor inside it)")
    replay.add_argument("--force", action="store_true", help="replace the run already in --out")

    port = commands.add_parser("port", help="write to or read from a running app's port")
    port_commands = port.add_subparsers(dest="port_command", required=True)
    write = port_commands.add_parser("write", help="post values to an input port")
    write.add_argument("app", help="app name (or app file)")
    write.add_argument("port")
    write.add_argument("values", nargs="+", type=float)
    read = port_commands.add_parser("read", help="print what an output port sends, from now on")
    read.add_argument("app", help="app name (or app file)")
    read.add_argument("port")
    read.add_argument("--count", type=int, default=10, help="rows to print, then exit (default 10)")
    read.add_argument("--queued", action="store_true",
                      help="start with the oldest samples still queued instead of the newest")
    port_commands.add_parser("list", help="list running apps and their ports")
    for sub in (write, read):
        sub.add_argument("--user", type=int, default=None, metavar="UID",
                         help="act on the app of this uid (root only; default: your own apps)")

    for name, (_module, text) in DELEGATED.items():
        commands.add_parser(name, help=text, add_help=False)

    model = commands.add_parser("model", help="inspect or build a 20-sim model or an FMU")
    model_commands = model.add_subparsers(dest="model_command", required=True)
    model_commands.add_parser("info", help="inputs, outputs, step size, kind (20-sim folder, FMU, python:)"
                              ).add_argument("path")
    build = model_commands.add_parser(
        "build", help="compile a 20-sim folder into its cached library, or an FMU source folder "
                      "(modelDescription.xml + sources/*.c) into an .fmu (default in the cache, never the source tree)")
    build.add_argument("path")
    build.add_argument("--out", type=Path, default=None, metavar="FILE.fmu",
                       help="where an FMU source folder's .fmu goes (default: ~/.cache/rtloop/fmu/<folder>.fmu)")
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in DELEGATED:
        import importlib

        try:
            module = importlib.import_module(DELEGATED[argv[0]][0])
        except ModuleNotFoundError as error:
            print(f"rtloop {argv[0]}: {missing_extra(error)}", file=sys.stderr)
            return exit_code_for(error)
        try:
            return int(module.main(argv[1:]) or 0)
        except RtloopError as error:
            print(f"rtloop {argv[0]}: {error}", file=sys.stderr)
            return exit_code_for(error)
    args = build_parser().parse_args(argv)
    try:
        return _dispatch(args)
    except BaseException as error:
        if args.debug and not isinstance(error, SystemExit | KeyboardInterrupt):
            _print_traceback(error)
        return _exit_code(error, args)


def _print_traceback(error: BaseException) -> None:
    import traceback

    cause = error.__cause__ or error.__context__
    shown = cause if cause is not None and isinstance(error, RtloopError) else error
    traceback.print_exception(shown, file=sys.stderr)


def _exit_code(error: BaseException, args: argparse.Namespace) -> int:
    """One line on stderr for an error, and the exit code it means."""
    if isinstance(error, SystemExit):
        raise error
    if isinstance(error, KeyboardInterrupt):
        print("rtloop: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if isinstance(error, TaskFailed):
        print(f"rtloop: {error}", file=sys.stderr)
        if error.traceback_text:
            print(error.traceback_text.rstrip(), file=sys.stderr)
        out = getattr(args, "out", None)
        if out is not None:
            print(f"rtloop: everything recorded until then is in {out}/", file=sys.stderr)
        return EXIT_TASK_FAILED
    if isinstance(error, RtloopError):
        print(f"rtloop: {error}", file=sys.stderr)
        return exit_code_for(error)
    if isinstance(error, ModuleNotFoundError):
        print(f"rtloop: {missing_extra(error)}", file=sys.stderr)
        return exit_code_for(error)
    # a bug: still one line; the traceback with --debug
    print(f"rtloop: internal error: {type(error).__name__}: {clip(str(error), 200)} "
          "(run with --debug for the traceback, and please report it)", file=sys.stderr)
    return EXIT_TASK_FAILED


def exit_code_for(error: BaseException) -> int:
    """The one rule: 2 for bad input (what the user gave is wrong or incomplete, a missing
    optional package included), 1 for a run that failed (a task's fault, a bug), 130 for Ctrl-C."""
    if isinstance(error, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    if isinstance(error, TaskFailed):
        return EXIT_TASK_FAILED
    if isinstance(error, ModuleNotFoundError | ValueError | LookupError | PermissionError):
        return EXIT_BAD_INPUT
    return EXIT_TASK_FAILED


def _dispatch(args: argparse.Namespace) -> int:
    if args.command in ("run", "simulate"):
        return _run(args)
    if args.command == "replay":
        return _replay(args)
    if args.command == "port":
        from rtloop.cli.port import cli_port

        return cli_port(args)
    if args.command == "model":
        from rtloop import models

        try:
            if args.model_command == "info":
                text = models.cli_model_info(args.path)
            else:
                text = models.cli_model_build(args.path, args.out)
        except models.ModelError as error:  # the model the user named cannot be used: bad input
            print(f"rtloop: {error}", file=sys.stderr)
            return EXIT_BAD_INPUT
        print(text)
        return 0
    raise AssertionError(args.command)


def _run(args: argparse.Namespace) -> int:
    from rtloop.app.appfile import load_app
    from rtloop.app.builder import check_duration

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
        from rtloop.runtime.supervisor import run

        try:
            summary = run(app, args.duration, args.out, trim=args.trim, keep_s=keep_s, force=args.force,
                          on_progress=show_progress if interactive else None)
        finally:
            if interactive:
                sys.stderr.write("\n")
    else:
        from rtloop.runtime.simulate import simulate

        summary = simulate(app, args.duration, args.out, trim=args.trim, keep_s=keep_s, force=args.force)
    if not args.quiet:
        print(format_summary(summary, args.out))
    return 0


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


def _replay(args: argparse.Namespace) -> int:
    from rtloop.runtime.replay import replay

    result = replay(args.run_dir, args.out, force=args.force)
    followed = (f"{result.skipped_releases} skipped releases, {result.stale_reads} stale reads and "
                f"{result.port_inputs} port inputs followed")
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
    return EXIT_TASK_FAILED


def show_progress(progress: Progress) -> None:
    """The run's progress line on the console (rewritten in place)."""
    until = "  (Ctrl-C stops)" if progress.duration_s is None else f" / {progress.duration_s:.1f} s"
    recording = "   RECORDING STOPPED" if progress.recording_stopped else ""
    lost = f"   LOST {progress.lost} records" if progress.lost else ""
    sys.stderr.write(f"\r  {progress.elapsed_s:7.1f} s{until}   deadline misses {progress.deadline_misses}   "
                     f"latency now {progress.latency_now_ns / 1e3:7.1f} µs{recording}{lost}  ")
    sys.stderr.flush()


def format_summary(summary: RunSummary, out: Path) -> str:
    """A short table of the run, with the non-real-time warning first."""
    lines: list[str] = []
    for name, task in summary.tasks.items():
        if not task.rt and summary.mode == "run":
            lines.append(f"WARNING: task {name!r} did NOT run real-time ({task.policy}): {task.rt_reason}")
    header = (f"{'task':<14}{'cycles':>8} {'sched':<12}{'cpu':>4}  {'latency µs p50/p99/max':<26}"
              f"{'exec µs p50/max':<18}{'misses':>7}{'overruns':>9}{'stale':>6}")
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
        lines.append(f"{name:<14}{t.cycles:>8} {sched:<12}{cpu:>4}  {latency:<26}{execution:<18}"
                     f"{t.deadline_misses:>7}{t.overruns:>9}{task.stale_reads:>6}")
        if task.host_exec_ns:
            host = task.host_exec_ns
            lines.append(f"  {name}: host execution time (not real time) mean {_us(host['mean'])} µs, "
                         f"max {_us(host['max'])} µs")
    for name, port in summary.ports.items():
        unread = port.direction == "out" and not port.received and port.dropped
        idle = " (nobody read it: the queue filled, then dropped)" if unread else ""
        lines.append(f"port {name} ({port.direction}, {port.signal}): {port.describe()}{idle}")
    lines += [f"note: {note}" for note in summary.notes]
    written = [name for name in ARTIFACTS if (out / name).exists()]
    lines.append(f"artifacts in {out}/: {', '.join(written)}")
    return "\n".join(lines)


def _us(value_ns: float) -> str:
    return "nan" if value_ns != value_ns else f"{value_ns / 1000:.1f}"


if __name__ == "__main__":
    sys.exit(main())
