"""The systemd unit of ``rtloop service APP.toml`` (``cli/service.py``): it runs an app until it is stopped.

The unit is printed (or written with ``--install``) with a comment above every setting saying
why it is there: real-time limits for a non-root user, where the recordings go, how a stop
reaches the supervisor (SIGINT, so the run ends the orderly way) and when systemd restarts it.
"""

from __future__ import annotations

import math
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from rtloop.errors import RtloopError
from rtloop.toolbox.run_history import MAX_RUNS_KEPT, history_prefix
from rtloop.version import __version__

if TYPE_CHECKING:  # annotations only: the command line imports this module to parse (no numpy)
    from rtloop.app.builder import App

UNIT_DIR = Path("/etc/systemd/system")
STATE_ROOT = Path("/var/lib/rtloop")
DEFAULT_KEEP_S = 60.0
USER_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]*\$?$")
CPU_LIST_PATTERN = re.compile(r"^\d+(-\d+)?(,\d+(-\d+)?)*$")
RECORDING_CLOSE_S = 25
"""Time allowed, after the tasks have stopped, to flush the recording and write ``summary.json``."""


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
        *_recording_lines(app, options),
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


def _recording_lines(app: App, options: ServiceOptions) -> list[str]:
    lines: list[str] = []
    state_dir = STATE_ROOT / app.name
    if options.out.parent == state_dir:
        lines += [
            f"# Recordings live in {state_dir}, created by systemd (owned by User= if set).",
            f"StateDirectory=rtloop/{app.name}",
        ]
    else:
        lines.append(f"# Recordings go to {options.out}: its folder must exist and be writable by the service's user.")
    prefix = history_prefix(options.out)
    set_aside = [str(Path(sys.executable).absolute()), "-m", "rtloop.toolbox.run_history", str(options.out)]
    lines += [
        f"# Each start records into {options.out.name}/; the run before is set aside as {prefix}NNNN-clean/,",
        "# -failed/ or -first-failure/ (the first failure after a clean run: in a restart burst, usually the",
        f"# informative one). At most {MAX_RUNS_KEPT} are kept: the oldest clean runs are removed first, then the",
        "# later failures of a burst, the first failures last; the newest two always stay.",
        "ExecStartPre=" + " ".join(quote_exec_argument(a) for a in set_aside),
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
    shared = sorted(set(parse_cpu_list(options.supervisor_cpus)) & set(rt_cpus))
    lines.append("# The supervisor (which also records) and the ROS 2 bridges run here; tasks still pin themselves.")
    if shared:
        lines.append(f"# WARNING: CPU {', '.join(map(str, shared))} is also a task's CPU: they compete there.")
    lines.append(f"CPUAffinity={options.supervisor_cpus}")
    return lines


def _stop_lines(app: App, name: str) -> list[str]:
    from rtloop.runtime.supervisor import STOP_GRACE_S  # the supervisor itself only when a unit is written

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
        "# fault (exit 1), a crash or a kill restarts the app after a second; so does a device not ready at",
        "# start (exit 3: an adapter that enumerates late, a drive powered after the computer, no answer yet).",
        "Restart=on-failure",
        "RestartSec=1",
        "# Exit 2 is a bad app file or option: restarting cannot fix it.",
        "RestartPreventExitStatus=2",
    ]


def _escape_specifiers(text: str) -> str:
    return text.replace("%", "%%")


def parse_cpu_list(text: str) -> list[int]:
    """A kernel CPU list (``0,2-3``) → its CPUs."""
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
            raise UnitFileInTheWay(f"{path} exists and differs from this unit; --force replaces it")
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        temporary.write_text(text)
        temporary.chmod(0o644)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return f"wrote {path}"


class UnitFileInTheWay(RtloopError, ValueError):
    """An existing, different unit file is in the way (bad input: exit 2)."""


SYSTEMD_UNIT_DIRS = tuple(Path(p) for p in ("/etc/systemd/system", "/run/systemd/system",
                                            "/usr/local/lib/systemd/system", "/usr/lib/systemd/system",
                                            "/lib/systemd/system"))
"""Where systemd looks for system units (systemd.unit(5)); a unit elsewhere must be linked."""
