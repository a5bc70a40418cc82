"""``rtloop reload``: load a controller's edited module into a running task, bumpless, at one release.

The module is kept in the run's folder (``code/``) and prepared in the task process outside its
loop (:mod:`rtloop.code_reload`); the request travels through the task's switch port, so it is
logged and ``rtloop replay`` reproduces it with the code the run kept.
"""

from __future__ import annotations

import argparse
import json
import os
import stat
import time
from pathlib import Path

from rtloop.errors import PortValueError

HELP = "load a controller's edited code into a running task, checked, at one release"

LEAD_S = 0.5
"""How far ahead of now the new code takes over when no --at-cycle is given: the task prepares it
(imports, builds, a dry step) in the meantime, outside its loop."""
ANSWER_TIMEOUT_S = 10.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("app", help="app name")
    parser.add_argument("task")
    parser.add_argument("controller", nargs="?", default=None,
                        help="the controller to reload (default: the active one); it becomes the active one")
    parser.add_argument("--file", type=Path, default=None,
                        help="the module to load (default: the file the controller's class came from)")
    parser.add_argument("--at-cycle", type=int, default=None, metavar="N",
                        help="the release from which the new code acts (default: about 0.5 s from now)")
    parser.add_argument("--user", type=int, default=None, metavar="UID",
                        help="act on the app of this uid (root only; default: your own apps)")


def run(args: argparse.Namespace) -> int:
    from rtloop.code_reload import code_file_name, code_id_of, compiled_code, compiled_file_name, result_file_name
    from rtloop.ipc.ports import connect_app
    from rtloop.ipc.switch_requests import release_at, release_cycle, switch_port_of

    app = connect_app(args.app, owner_uid=args.user, command="reload")
    port = switch_port_of(app, args.task, args.controller, "reload")
    current = app.peek(port.port)
    name = args.controller if args.controller is not None else port.controllers[int(current[0])]
    source_path = args.file if args.file is not None else _registered_source(app.ports[port.port], name)
    source = _read_source(source_path)
    try:
        compile(source, str(source_path), "exec")
    except SyntaxError as error:
        raise PortValueError(f"{source_path}:{error.lineno}: {error.msg}: not loaded; the old code keeps "
                             "running") from None
    code_id = code_id_of(source)
    if float(code_id) == float(current[3]) and name == port.controllers[int(current[0])]:
        # the task passes a code on to its reload thread once: it would wait for an answer that never comes
        raise PortValueError(f"{source_path}: task {args.task!r} was asked for this very code for {name} already "
                             f"(code {code_id:012x}, at cycle {int(current[1])}): nothing new to load; edit the "
                             "file first, or give another one with --file")
    run_dir = _run_dir(app.registry)
    code_dir = run_dir / "code"
    _keep(code_dir, code_file_name(name, code_id), source)
    # compiled here, not in the task: a module's compilation holds the task's interpreter lock for milliseconds
    _keep(code_dir, compiled_file_name(name, code_id),
          compiled_code(source, code_dir / code_file_name(name, code_id), code_id))
    t0_ns, at_ns = release_at(app, port, args.at_cycle, LEAD_S, "reload")
    at_cycle = release_cycle(at_ns - t0_ns, port, args.at_cycle)  # past 2**53: named, not the port's range
    at_ns = t0_ns + at_cycle * port.period_ns  # the release itself
    result_path = code_dir / result_file_name(name, code_id)
    result_path.unlink(missing_ok=True)  # the answer to this request, not to an earlier one
    app.write(port.port, [float(port.controllers.index(name)), float(at_cycle), float(current[2]), float(code_id)])
    result = _wait_for(result_path, at_ns)
    where = f"at cycle {at_cycle} (t = {at_cycle * port.period_ns / 1e9:.6f} s)"
    if result is None:
        raise PortValueError(f"task {args.task!r} gave no answer about the new code within {ANSWER_TIMEOUT_S:g} s "
                             f"(is the task running?); it takes over {where} only if it was ready by then")
    if not result.get("accepted"):
        raise PortValueError(f"{source_path}: refused: {result.get('reason')}; the old code keeps running")
    if _number(result.get("ready_ns")) > at_ns:
        raise PortValueError(f"{source_path}: checked, but ready only after {where}: not used; ask again with a "
                             "later --at-cycle")
    timeline = result.get("timeline_ns")
    prepared = ""
    if isinstance(timeline, dict) and _number(timeline.get("asked")):
        prepared = (f"; prepared in {(_number(result.get('ready_ns')) - _number(timeline.get('asked'))) / 1e6:.1f} ms "
                    f"beside the loop (it waited for {_number(result.get('slack_waits'))} of its releases)")
    print(f"{args.task}: {name} reloaded from {source_path} (code {code_id:012x}), acting {where}; "
          f"dry step {_number(result.get('dry_step_ns')) / 1e3:.0f} µs{prepared}")
    return 0


def _number(value: object) -> int:
    return int(value) if isinstance(value, int | float) else 0


def _registered_source(info: dict[str, object], name: str) -> Path:
    sources = info.get("sources")
    found = sources.get(name) if isinstance(sources, dict) else None
    if not isinstance(found, str):
        raise PortValueError(f"controller {name!r}: the app does not say which file its code came from; "
                             "give it with --file")
    return Path(found)


SOURCE_MAX_BYTES = 16 << 20
"""A module larger than this is refused: it is read and compiled whole here, and kept in the run's folder."""


def _read_source(path: Path) -> bytes:
    """The module's bytes; a FIFO (which blocks forever), a device (/dev/zero behind a link: read until
    memory runs out), a folder or a file over :data:`SOURCE_MAX_BYTES` refused before reading."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # non-blocking: opening a FIFO waits for a writer
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise PortValueError(f"{path}: not a regular file, so not a module to load; the old code keeps running")
        with os.fdopen(fd, "rb") as file:
            source = file.read(SOURCE_MAX_BYTES + 1)  # a file growing meanwhile stops here
    except OSError as error:
        raise PortValueError(f"{path}: {error.strerror}") from None
    if len(source) > SOURCE_MAX_BYTES:
        raise PortValueError(f"{path}: more than {SOURCE_MAX_BYTES >> 20} MiB, not a controller's module; the old "
                             "code keeps running")
    return source


def _run_dir(registry: dict[str, object]) -> Path:
    summary = registry.get("summary")
    if not isinstance(summary, str):
        raise PortValueError("this app keeps no run folder: its code cannot be reloaded")
    return Path(summary).parent


def _keep(code_dir: Path, file_name: str, source: bytes) -> None:
    """The code, in the run's folder, as this user's file (the task loads only such a file)."""
    try:
        code_dir.mkdir(mode=0o700, exist_ok=True)
        info = os.lstat(code_dir)
        if info.st_uid != os.geteuid() or not os.path.isdir(code_dir) or os.path.islink(code_dir):
            raise PortValueError(f"{code_dir} is not a folder of yours; not used")
        path = code_dir / file_name
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        except FileExistsError:
            return  # the same content (its name is its hash): kept already
        with os.fdopen(fd, "wb") as file:
            file.write(source)
    except OSError as error:
        raise PortValueError(f"{code_dir}: {error.strerror}: the new code could not be kept") from None


def _wait_for(path: Path, at_ns: int) -> dict[str, object] | None:
    deadline = time.monotonic() + ANSWER_TIMEOUT_S + max(0.0, (at_ns - time.clock_gettime_ns(time.CLOCK_MONOTONIC))
                                                         / 1e9)
    while time.monotonic() < deadline:
        try:
            answer = json.loads(path.read_text())
            return answer if isinstance(answer, dict) else None
        except (OSError, ValueError):
            time.sleep(0.05)
    return None
