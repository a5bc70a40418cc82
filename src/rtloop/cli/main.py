"""The ``rtloop`` command line: one argparse tree for every command.

Each command lives in a module of this package that declares its arguments
(``add_arguments(parser)``) and runs from the parsed namespace (``run(args)``). Those
modules import nothing heavy at the top: building the whole tree (``rtloop --help``,
a usage error, shell completion) loads no engine, and a command imports its engine
(matplotlib, rich, DDS, the supervisor) only when it runs.
"""

from __future__ import annotations

import argparse
import errno
import sys
from collections.abc import Callable
from types import ModuleType

from rtloop.cli import (
    bench,
    bridge,
    devices,
    doctor,
    emulate,
    model,
    port,
    reload,
    replay,
    report,
    run,
    service,
    sweep,
    switch,
    top,
    why,
)
from rtloop.cli.arguments import EXIT_BAD_INPUT, EXIT_DEVICE_NOT_READY, EXIT_FAILED, EXIT_INTERRUPTED, CommandParser
from rtloop.errors import DeviceNotReady, RtloopError, TaskFailed
from rtloop.text import clip
from rtloop.version import __version__

EXIT_TASK_FAILED = EXIT_FAILED

# name → the module that declares and runs it, in the order `rtloop --help` lists them
COMMANDS: dict[str, ModuleType] = {
    "run": run, "simulate": run, "replay": replay, "port": port, "switch": switch, "reload": reload, "model": model,
    "report": report, "top": top, "doctor": doctor, "bridge": bridge, "bench": bench, "service": service,
    "io": devices, "sweep": sweep, "why": why, "emulate": emulate,
}

# What the OS says of a path that cannot be used as given (not of a device or a disk that failed).
PATH_ERRNOS = frozenset({errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.EACCES, errno.EPERM, errno.EROFS,
                         errno.EEXIST, errno.ENAMETOOLONG, errno.ELOOP})

# Optional packages and the extra that installs them (the core needs numpy only).
EXTRAS = {"mcap": "ros", "mcap_ros2": "ros", "cyclonedds": "ros", "rich": "report", "matplotlib": "report",
          "fmpy": "fmu", "foxglove": "live", "serial": "serial", "pysoem": "ethercat"}


def missing_extra(error: ModuleNotFoundError) -> str:
    """One line for a missing optional package: what is missing and what installs it."""
    top_name = (error.name or "").split(".")[0]
    extra = EXTRAS.get(top_name)
    if extra is None:
        return f"the Python package {top_name!r} is missing"
    return f"needs the optional package {top_name!r}: pip install 'rtloop[{extra}]'"


def build_parser() -> argparse.ArgumentParser:
    """The whole tree: every command's arguments, each with the function that runs it (``args.handler``)."""
    parser = CommandParser(prog="rtloop", description="Real-time control loops in Python on Linux.")
    parser.add_argument("--version", action="version", version=f"rtloop {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=CommandParser)
    for name, module in COMMANDS.items():
        help_text, add_arguments, handler = command_parts(module, name)
        sub = commands.add_parser(name, help=help_text, description=help_text[:1].upper() + help_text[1:] + ".")
        add_arguments(sub)
        sub.set_defaults(handler=handler, command_prog=sub.prog)
    return parser


def command_parts(module: ModuleType, name: str) -> tuple[str, Callable[[argparse.ArgumentParser], None],
                                                          Callable[[argparse.Namespace], int]]:
    """A command module's help line, argument declarations and runner; ``run`` and ``simulate`` share one."""
    parts: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]] \
        | None = getattr(module, "COMMANDS", None)
    if parts is not None:
        return parts[name]
    return module.HELP, module.add_arguments, module.run


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``rtloop``: the exit code (0, 1 failed run, 2 bad input, 130 Ctrl-C)."""
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)  # a usage error: exit 2
    try:
        return int(args.handler(args) or 0)
    except BaseException as error:
        if getattr(args, "debug", False) and not isinstance(error, SystemExit | KeyboardInterrupt):
            _print_traceback(error)
        return _exit_code(error, args)


def _print_traceback(error: BaseException) -> None:
    import traceback

    cause = error.__cause__ or error.__context__
    shown = cause if cause is not None and isinstance(error, RtloopError) else error
    traceback.print_exception(shown, file=sys.stderr)


def _exit_code(error: BaseException, args: argparse.Namespace) -> int:
    """One line on stderr for an error, naming the command, and the exit code it means."""
    prefix = args.command_prog
    if isinstance(error, SystemExit):
        raise error
    if isinstance(error, KeyboardInterrupt):
        print(f"{prefix}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if isinstance(error, TaskFailed):
        print(f"{prefix}: {error}", file=sys.stderr)
        if error.traceback_text and (getattr(args, "debug", False) or not error.said_in_full):
            print(error.traceback_text.rstrip(), file=sys.stderr)
        out = getattr(args, "out", None)
        if out is not None:
            print(f"{prefix}: everything recorded until then is in {out}/", file=sys.stderr)
        return EXIT_TASK_FAILED
    if isinstance(error, RtloopError):
        print(f"{prefix}: {error}", file=sys.stderr)
        return exit_code_for(error)
    if isinstance(error, ModuleNotFoundError):
        print(f"{prefix}: {missing_extra(error)}", file=sys.stderr)
        return exit_code_for(error)
    if isinstance(error, OSError) and error.strerror:  # a file: where and why, as the OS says it
        where = f"{error.filename}: " if error.filename else ""
        print(f"{prefix}: {where}{error.strerror}", file=sys.stderr)
        return exit_code_for(error)
    # a bug: still one line; the traceback with --debug
    print(f"{prefix}: internal error: {type(error).__name__}: {clip(str(error), 200)} "
          "(run with --debug for the traceback, and please report it)", file=sys.stderr)
    return EXIT_TASK_FAILED


def exit_code_for(error: BaseException) -> int:
    """The one rule: 2 for bad input (what the user gave is wrong or incomplete, a missing
    optional package or a path that cannot be used included), 1 for a run that failed (a task's
    fault, a full disk, a bug), 3 for a device declared right that refused at start (not there
    yet, busy, silent: a service retries it), 130 for Ctrl-C."""
    if isinstance(error, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    if isinstance(error, TaskFailed):
        return EXIT_TASK_FAILED
    if isinstance(error, DeviceNotReady):
        return EXIT_DEVICE_NOT_READY
    if isinstance(error, ModuleNotFoundError | ValueError | LookupError | PermissionError):
        return EXIT_BAD_INPUT
    if isinstance(error, OSError) and not isinstance(error, RtloopError) and error.errno in PATH_ERRNOS:
        return EXIT_BAD_INPUT  # a path the user gave that cannot be opened or written (a full disk is not)
    return EXIT_TASK_FAILED


if __name__ == "__main__":
    sys.exit(main())
