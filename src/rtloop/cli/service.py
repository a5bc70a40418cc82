"""``rtloop service APP.toml``: a systemd unit that runs an app until it is stopped.

The unit is printed (or written with ``--install``) with a comment above every setting saying
why it is there: real-time limits for a non-root user, where the recordings go, how a stop
reaches the supervisor (SIGINT, so the run ends the orderly way) and when systemd restarts it.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

from rtloop.app.appfile import load_app
from rtloop.app.builder import App
from rtloop.errors import AppError
from rtloop.runtime.supervisor import STOP_GRACE_S
from rtloop.version import __version__

EXIT_BAD_INPUT = 2
EXIT_CANNOT_WRITE = 1
UNIT_DIR = Path("/etc/systemd/system")
STATE_ROOT = Path("/var/lib/rtloop")
DEFAULT_KEEP_S = 60.0
RECORDING_CLOSE_S = 25
"""Time allowed, after the tasks have stopped, to flush the recording and write ``summary.json``."""
USER_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]*\$?$")
CPU_LIST_PATTERN = re.compile(r"^\d+(-\d+)?(,\d+(-\d+)?)*$")


@dataclass(frozen=True, slots=True)
class ServiceOptions:
    """What the unit is made from, besides the app."""

    app_file: Path
    """Absolute path of the app file (the service reads it at every start)."""
    out: Path
    """Absolute directory of the recordings of the current run."""
    keep_s: float
    """``--keep``: seconds of recording kept (plus the cycles around every miss or fault)."""
    user: str | None = None
    """``User=``; ``None``: root."""
    supervisor_cpus: str | None = None
    """``CPUAffinity=`` of the supervisor and everything it starts, as a kernel CPU list."""
    ros_domain_id: str | None = None
    """``ROS_DOMAIN_ID`` to pass to the ROS 2 bridges (from the environment of ``rtloop service``)."""


def unit_name(app: App) -> str:
    return f"rtloop-{app.name}.service"


def default_out(app: App) -> Path:
    return STATE_ROOT / app.name / "latest"


def rtloop_command() -> list[str]:
    """The rtloop executable in use: the ``rtloop`` script beside this Python, else ``python -m``."""
    python = Path(sys.executable).absolute()  # not resolved: a venv's python is a symlink out of the venv
    script = python.parent / "rtloop"
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    return [str(python), "-m", "rtloop.cli"]


def quote_exec_argument(argument: str) -> str:
    """One ExecStart= word: specifiers (``%``) and variables (``$``) doubled, quoted if needed."""
    text = argument.replace("\\", "\\\\").replace("%", "%%").replace("$", "$$")
    if any(c.isspace() for c in text) or any(c in text for c in "\"';") or not text:
        text = '"' + text.replace('"', '\\"') + '"'
    return text


def render_unit(app: App, options: ServiceOptions) -> str:
    """The unit file's text."""
    name = unit_name(app)
    out = options.out
    previous = out.with_name("previous" if out.name == "latest" else f"{out.name}.previous")
    exec_start = [*rtloop_command(), "run", str(options.app_file), "--out", str(out), "--keep", f"{options.keep_s:g}"]
    regenerate = f"rtloop service {options.app_file} --install --force"
    lines = [
        f"# {name}: runs the rtloop app {app.name!r} until it is stopped. Written by `rtloop service`",
        f"# (rtloop {__version__}); regenerate it rather than edit it: {regenerate}",
        f"# Logs: journalctl -u {name}",
        "",
        "[Unit]",
        f"Description={_escape_specifiers(f'rtloop app {app.name} ({options.app_file})')}",
    ]
    if app.ros_topics:
        lines += [
            "# The ROS 2 bridges discover their peers over the network: start once it is up.",
            "Wants=network-online.target",
            "After=network-online.target",
        ]
    lines += [
        "# An app that keeps failing is not restarted more than 5 times a minute; after that the unit",
        f"# stays failed until `systemctl reset-failed {name}`.",
        "StartLimitIntervalSec=60",
        "StartLimitBurst=5",
        "",
        "[Service]",
        "# exec: `systemctl start` fails at once if the rtloop executable cannot be started.",
        "Type=exec",
        *_recording_lines(app, options, previous),
        f"# No --duration: the run lasts until it is stopped. --keep {options.keep_s:g}: the recording holds the",
        "# last seconds of the run plus the cycles around every deadline miss, stale read or fault.",
        "ExecStart=" + " ".join(quote_exec_argument(a) for a in exec_start),
        "# Python writes the console lines to the journal as they come, not in blocks.",
        "Environment=PYTHONUNBUFFERED=1",
        *_ros_lines(app, options),
        *_realtime_lines(app, options),
        *_cpu_lines(app, options),
        *_stop_lines(app, name),
        "",
        "[Install]",
        "# Started at boot by `systemctl enable`.",
        "WantedBy=multi-user.target",
    ]
    return "\n".join(lines) + "\n"


def _recording_lines(app: App, options: ServiceOptions, previous: Path) -> list[str]:
    lines: list[str] = []
    state_dir = STATE_ROOT / app.name
    if options.out.parent == state_dir:
        lines += [
            f"# Recordings live in {state_dir}, created by systemd (owned by User= if set).",
            f"StateDirectory=rtloop/{app.name}",
        ]
    else:
        lines.append(f"# Recordings go to {options.out}: its folder must exist and be writable by the service's user.")
    lines += [
        f"# Each start records into {options.out.name}/; the run before is kept as {previous.name}/ (after a",
        "# restart: the run that failed). Two runs at most on disk. '-': nothing to move at the first start.",
        f"ExecStartPre=-/bin/rm -rf {quote_exec_argument(str(previous))}",
        f"ExecStartPre=-/bin/mv -T {quote_exec_argument(str(options.out))} {quote_exec_argument(str(previous))}",
    ]
    return lines


def _ros_lines(app: App, options: ServiceOptions) -> list[str]:
    if not any(topic.domain_id is None for topic in app.ros_topics):
        return []  # no bridges, or the app file names its DDS domain itself
    if options.ros_domain_id is not None:
        return [
            "# The ROS 2 bridges' DDS domain (the app file names none), taken from `rtloop service`'s environment.",
            f"Environment=ROS_DOMAIN_ID={options.ros_domain_id}",
        ]
    return ["# The ROS 2 bridges use DDS domain 0: the app file names none and ROS_DOMAIN_ID was not set."]


def _realtime_lines(app: App, options: ServiceOptions) -> list[str]:
    realtime = [s.config for s in app.tasks.values() if s.config.policy in ("fifo", "rr")]
    highest = max((c.priority for c in realtime), default=0)
    asked = f"this app asks up to {highest}" if realtime else "this app asks for none today"
    lines = [
        "# Real time without root: tasks call sched_setscheduler(SCHED_FIFO/RR) themselves, which a",
        f"# non-root user may do up to RLIMIT_RTPRIO ({asked}; 99 so that raising a priority in",
        "# the app file needs no new unit). Root does not need it (CAP_SYS_NICE); it costs nothing.",
        "LimitRTPRIO=99",
        "# Every task locks its memory (mlockall): no page faults in the loop. RLIMIT_MEMLOCK is 8 MB",
        "# by default, far too little for a Python process; root does not need it (CAP_IPC_LOCK).",
        "LimitMEMLOCK=infinity",
    ]
    deadline = [s.name for s in app.tasks.values() if s.config.policy == "deadline"]
    if options.user is None:
        lines += [
            "# Runs as root. `rtloop service --user NAME` runs it as NAME instead: the limits above give",
            "# its tasks real time; only /dev/cpu_dma_latency (idle states held shallow) stays root-only.",
        ]
        return lines
    lines += [
        f"# Runs as {options.user}, not root: real time comes from the limits above. /dev/cpu_dma_latency is",
        "# root-only: CPUs may enter deep idle states (summary.json: cpu_dma_latency_held; `rtloop doctor`).",
        f"User={options.user}",
    ]
    if deadline:
        lines += [
            f"# SCHED_DEADLINE (task {', '.join(deadline)}) needs CAP_SYS_NICE: no rlimit allows it.",
            "AmbientCapabilities=CAP_SYS_NICE",
        ]
    return lines


def _cpu_lines(app: App, options: ServiceOptions) -> list[str]:
    pinned = {s.name: s.config.cpu for s in app.tasks.values() if s.config.cpu is not None}
    unpinned = [s.name for s in app.tasks.values() if s.config.cpu is None]
    rt_cpus = sorted(set(pinned.values()))
    placement = ", ".join(f"{task} → CPU {cpu}" for task, cpu in pinned.items()) or "none pinned"
    lines = [f"# CPU placement: the tasks pin themselves ({placement})."]
    if unpinned:
        lines.append(f"# Not pinned: {', '.join(unpinned)} (runs on the CPUs given below, if any).")
    if options.supervisor_cpus is None:
        lines += [
            "# The supervisor (which also records) and the ROS 2 bridges are not real-time; to keep them off",
            "# the tasks' CPUs: `rtloop service ... --supervisor-cpus LIST` (sets CPUAffinity=; tasks still pin",
        "# themselves; unpinned tasks run there too).",
        ]
        return lines
    shared = sorted(set(_parse_cpu_list(options.supervisor_cpus)) & set(rt_cpus))
    lines.append("# The supervisor (which also records) and the ROS 2 bridges run here; tasks still pin themselves.")
    if shared:
        lines.append(f"# WARNING: CPU {', '.join(map(str, shared))} is also a task's CPU: they compete there.")
    lines.append(f"CPUAffinity={options.supervisor_cpus}")
    return lines


def _stop_lines(app: App, name: str) -> list[str]:
    longest_period_s = max(s.config.period_ns for s in app.tasks.values()) / 1e9
    stop_timeout_s = math.ceil(STOP_GRACE_S + longest_period_s) + RECORDING_CLOSE_S
    return [
        "# `systemctl stop` sends SIGINT (as Ctrl-C does) to the supervisor only: it stops the tasks at a",
        "# cycle boundary, closes the recording, writes summary.json and exits 0. The tasks and ROS 2",
        "# bridges are its children; it stops them in order (mixed: leftovers get SIGKILL at the end).",
        "KillSignal=SIGINT",
        "KillMode=mixed",
        f"# The supervisor gives the tasks {STOP_GRACE_S:g} s (+ one period) to stop, then kills them; the rest",
        "# is for closing the recording. Past this, systemd sends SIGKILL.",
        f"TimeoutStopSec={stop_timeout_s}",
        "# Success: exit 0 (a requested stop) or death by SIGINT/SIGTERM, systemd's defaults. A task",
        "# fault (exit 1), a crash or a kill restarts the app after a second.",
        "Restart=on-failure",
        "RestartSec=1",
        "# Exit 2 is a bad app file or option: restarting cannot fix it.",
        "RestartPreventExitStatus=2",
    ]


def _escape_specifiers(text: str) -> str:
    return text.replace("%", "%%")


def _parse_cpu_list(text: str) -> list[int]:
    cpus: list[int] = []
    for part in text.split(","):
        low, _, high = part.partition("-")
        cpus.extend(range(int(low), int(high or low) + 1))
    return cpus


def install(text: str, path: Path, *, force: bool) -> str:
    """Write the unit to ``path`` (atomically); refuses to replace a different unit unless ``force``."""
    if path.exists():
        if path.read_text() == text:
            return f"{path} is already this unit; nothing written"
        if not force:
            raise _Refused(f"{path} exists and differs from this unit; --force replaces it")
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        temporary.write_text(text)
        temporary.chmod(0o644)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return f"wrote {path}"


class _Refused(Exception):
    """An existing, different unit file is in the way."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rtloop service",
        description="Print a systemd unit that runs an app until stopped (or install it with --install).",
    )
    parser.add_argument("app", help="app file (TOML)")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR",
                        help=f"recordings of the current run (default {STATE_ROOT}/APP/latest)")
    parser.add_argument("--keep", type=float, default=DEFAULT_KEEP_S, metavar="S",
                        help=f"seconds of recording kept, plus the cycles around faults (default {DEFAULT_KEEP_S:g})")
    parser.add_argument("--user", default=None, metavar="NAME", help="run as this user instead of root")
    parser.add_argument("--supervisor-cpus", default=None, metavar="LIST",
                        help="CPUs for the supervisor and bridges, e.g. 0 or 0,2-3 (default: leave unset)")
    parser.add_argument("--install", action="store_true", help="write the unit instead of printing it")
    parser.add_argument("--unit-dir", type=Path, default=UNIT_DIR, metavar="DIR",
                        help=f"where --install writes (default {UNIT_DIR})")
    parser.add_argument("--force", action="store_true", help="with --install: replace a different existing unit")
    return parser


SYSTEMD_UNIT_DIRS = tuple(Path(p) for p in ("/etc/systemd/system", "/run/systemd/system",
                                            "/usr/local/lib/systemd/system", "/usr/lib/systemd/system",
                                            "/lib/systemd/system"))
"""Where systemd looks for system units (systemd.unit(5)); a unit elsewhere must be linked."""


def _check_options(args: argparse.Namespace) -> str | None:
    """The first problem with the options, as one line; ``None`` if none."""
    if not args.keep > 0 or not math.isfinite(args.keep):
        return f"--keep {args.keep:g}: expected seconds > 0"
    if args.user is not None and not USER_PATTERN.match(args.user):
        return f"--user {args.user!r}: not a user name"
    if args.supervisor_cpus is not None and not CPU_LIST_PATTERN.match(args.supervisor_cpus):
        return f"--supervisor-cpus {args.supervisor_cpus!r}: expected a CPU list such as 0 or 0,2-3"
    if args.supervisor_cpus is not None and not _parse_cpu_list(args.supervisor_cpus):
        return f"--supervisor-cpus {args.supervisor_cpus!r}: a range runs low-high"
    for option, path in (("app file", args.app), ("--out", args.out)):
        if path is not None and any(not c.isprintable() for c in str(path)):
            return f"{option} {str(path)!r}: contains a control character"
    if args.out is not None and Path(args.out).absolute() == Path("/"):
        return "--out /: choose a folder of its own"
    domain = os.environ.get("ROS_DOMAIN_ID")
    if domain is not None and not domain.isdigit():
        return f"ROS_DOMAIN_ID={domain!r} in the environment: expected a number"
    return None


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    problem = _check_options(args)
    if problem is not None:
        print(f"rtloop service: {problem}", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        app = load_app(args.app)
    except AppError as error:
        print(f"rtloop service: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    options = ServiceOptions(
        app_file=Path(args.app).absolute(),
        out=Path(args.out).absolute() if args.out is not None else default_out(app),
        keep_s=args.keep,
        user=args.user,
        supervisor_cpus=args.supervisor_cpus,
        ros_domain_id=os.environ.get("ROS_DOMAIN_ID"),
    )
    text = render_unit(app, options)
    if not args.install:
        sys.stdout.write(text)
        return 0
    if not args.unit_dir.is_dir():
        print(f"rtloop service: --unit-dir {args.unit_dir}: no such folder (create it, or leave --unit-dir out "
              f"to install into {UNIT_DIR})", file=sys.stderr)
        return EXIT_BAD_INPUT
    path = args.unit_dir / unit_name(app)
    try:
        message = install(text, path, force=args.force)
    except _Refused as refusal:
        print(f"rtloop service: {refusal}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as error:
        print(f"rtloop service: cannot write {path}: {error.strerror}", file=sys.stderr)
        return EXIT_CANNOT_WRITE
    print(message)
    if args.unit_dir.resolve() in SYSTEMD_UNIT_DIRS:
        print("next:")
        print("  systemctl daemon-reload")
    else:  # systemd never reads this folder by itself: link the file (which also reloads)
        print(f"next (systemd does not look in {args.unit_dir} by itself):")
        print(f"  systemctl link {path.absolute()}")
    print(f"  systemctl enable --now {unit_name(app)}")
    print(f"  journalctl -u {unit_name(app)} -f")
    return 0


if __name__ == "__main__":
    sys.exit(main())
