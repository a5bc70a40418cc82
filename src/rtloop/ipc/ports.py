"""Reaching a running app from non-real-time code: by app name, then by port name.

    from rtloop.ipc.ports import connect_app
    app = connect_app("jiwy")
    app.write("setpoint", [0.5, 0.3])          # validated here; the task never sees a bad value
    with app.reader("angles") as reader:        # one reader at a time per output port
        ticks, rows = reader.read(100)         # up to 100 ticks since the last read

A running supervisor describes its ports in a registry file next to its shared memory;
``rtloop port write/read/list`` are thin wrappers over this module.

Trust: a registry is believed only when its file is owned by the (effective) uid of the
live supervisor it names, its name and content agree, and every segment it lists is a
valid name of that same run owned by that same uid. By default only apps of the
caller's own uid are considered; root acts on another user's app only when it says so
(``owner_uid=`` / ``rtloop port --user UID``). See docs/security.md.
"""

from __future__ import annotations

import difflib
import fcntl
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.errors import PortValueError, RtloopError
from rtloop.ipc.channels import LatestValue
from rtloop.ipc.ring import SampleQueue
from rtloop.ipc.segments import (
    SEGMENT_NAME,
    SHM_DIR,
    Segment,
    SegmentDenied,
    SegmentRefused,
    open_in_shm,
    pid_alive,
    process_start_ticks,
    process_uid,
)
from rtloop.ipc.status import CONTROL_WORDS, STATUS_WORDS, StatusWord, WordBlock, read_epoch
from rtloop.ipc.values import validate_values
from rtloop.text import shorten

REGISTRY_MAX_BYTES = 1 << 20


class AppNotRunning(RtloopError, LookupError):
    """No running app of that name was found."""


class AppNotReachable(RtloopError, PermissionError):
    """An app of that name runs, but this caller may not (or chose not to) act on it."""


@dataclass(frozen=True)
class RunningApp:
    """A live app found through its registry file (already checked: see the module doc)."""

    name: str
    pid: int
    registry: dict[str, Any]
    path: Path
    uid: int = -1
    """Owner of the registry and of every segment of the run: the supervisor's uid."""

    def segment(self, name: str) -> Segment:
        """Attach one of this run's segments, refusing names of other runs or other owners."""
        prefix = self.path.name.removesuffix("registry.json")
        if not isinstance(name, str) or not name.startswith(prefix) or not SEGMENT_NAME.fullmatch(name):
            raise SegmentRefused(f"registry {self.path.name} lists segment {shorten(name)}, "
                                 "which is not a segment of that run; not used")
        return Segment.attach(name, owner_uid=self.uid if self.uid >= 0 else None)

    @property
    def ports(self) -> dict[str, dict[str, Any]]:
        ports: dict[str, dict[str, Any]] = self.registry["ports"]
        return ports

    def _port(self, name: str, direction: str) -> dict[str, Any]:
        info = self.ports.get(name)
        if info is None:
            close = difflib.get_close_matches(str(name), list(self.ports), n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise PortValueError(f"app {self.name!r} has no port {name!r}; {hint}its ports are {sorted(self.ports)}")
        if info["direction"] != direction:
            verb = "written" if direction == "in" else "read"
            raise PortValueError(f"port {name!r} of app {self.name!r} goes {info['direction']}; it cannot be {verb}")
        return info

    def write(self, port: str, values: list[float] | np.ndarray) -> None:
        """Post values to an input port once; rejects wrong lengths and NaN/inf (unless allowed).
        A client that writes again and again holds a :meth:`writer` instead (mapped once)."""
        with self.writer(port) as writer:
            writer.write(values)

    def writer(self, port: str) -> PortWriter:
        """A writer of an input port, its segment mapped until closed (any number of writers)."""
        return PortWriter(self, port, self._port(port, "in"))

    def peek(self, port: str) -> np.ndarray:
        """The value an input port holds now (what its task reads at its next release)."""
        info = self._port(port, "in")
        segment = self.segment(info["segment"])
        try:
            values = LatestValue(segment).peek()
        finally:
            segment.close()
        if values is None or len(values) != info["size"]:
            raise SegmentRefused(f"port {port!r}: its value could not be read (a writer held it)")
        return values

    def epoch_ns(self) -> int:
        """The run's T0 (CLOCK_MONOTONIC ns), 0 while the tasks have not started."""
        segment = self.segment(self.registry["control"])
        try:
            t0_ns, _end_ns = read_epoch(WordBlock(segment, 0, CONTROL_WORDS))
        finally:
            segment.close()
        return t0_ns

    def reader(self, port: str) -> PortReader:
        """The single reader of an output port (held until closed)."""
        return PortReader(self, port, self._port(port, "out"))

    @property
    def runs_live(self) -> bool:
        """A real-time run (``rtloop run``), not a simulation: only these hold their name."""
        return bool(self.registry.get("mode", "run") != "simulate")

    def alive(self) -> bool:
        """Whether the app's supervisor is still running."""
        return pid_alive(self.pid) and self.path.exists()

    def task_pids(self) -> dict[str, int]:
        """PID of each task process (0 until it has started)."""
        pids: dict[str, int] = {}
        for task, segment_name in self.registry["tasks"].items():
            segment = self.segment(segment_name)
            pids[task] = WordBlock(segment, 0, STATUS_WORDS)[StatusWord.PID]
        return pids


class PortWriter:
    """Writes values to an input port, its segment mapped once (the reader's counterpart). Several
    writers may hold the same port: each write takes the segment's lock for its own duration only,
    and the real-time task that reads the port never waits for it (a seqlock)."""

    def __init__(self, app: RunningApp, name: str, info: dict[str, Any]) -> None:
        self.name = name
        self.where = f"port {name!r} ({info['signal']})"
        self.size, self.allow_nonfinite, self.value_range = int(info["size"]), bool(info["allow_nonfinite"]), \
            port_range(info)
        self.segment = app.segment(info["segment"])
        try:
            self.channel = LatestValue(self.segment)
            if self.channel.n_values != self.size:
                raise SegmentRefused(f"port {name!r}: its segment holds {self.channel.n_values} values, "
                                     f"the registry says {self.size}; not used")
        except BaseException:
            self.segment.close()
            raise

    def write(self, values: list[float] | np.ndarray) -> None:
        """Post values; rejects wrong lengths, NaN/inf (unless allowed) and values out of the port's range."""
        array = validate_values(values, self.size, allow_nonfinite=self.allow_nonfinite, where=self.where,
                                value_range=self.value_range)
        if self.channel.fed_by_profile:
            raise PortValueError(f"port {self.name!r} is fed from a profile in this run; live writes are refused "
                                 '(nudge = "offset" or "override" on the port combines them with the profile)')
        fcntl.flock(self.segment.fd, fcntl.LOCK_EX)  # writers serialise; the RT reader never waits
        try:
            self.channel.write(array)
        finally:
            fcntl.flock(self.segment.fd, fcntl.LOCK_UN)

    def close(self) -> None:
        self.segment.close()

    def __enter__(self) -> PortWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PortReader:
    """Reads every tick an output port sends. One reader per port at a time (flock)."""

    def __init__(self, app: RunningApp, name: str, info: dict[str, Any]) -> None:
        self.name = name
        self.segment = app.segment(info["segment"])
        try:
            fcntl.flock(self.segment.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self.segment.close()
            raise PortValueError(f"port {name!r} of app {app.name!r} already has a reader") from None
        self.queue = SampleQueue(self.segment)
        self.period_ns = int(info["period_ns"])

    def read(self, max_rows: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(ticks, rows) sent since the last read, oldest first; never blocks."""
        return self.queue.drain(max_rows)

    def skip_to_newest(self, keep_rows: int = 1) -> int:
        """Discard all but the newest ``keep_rows`` waiting rows (a reader that wants 'now'); returns how many."""
        waiting = self.queue.sent - self.queue.received
        skipped = max(0, waiting - keep_rows)
        if skipped:
            self.queue.drain(skipped)
        return skipped

    def close(self) -> None:
        self.segment.close()  # closing the descriptor releases the flock

    def __enter__(self) -> PortReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def port_range(info: dict[str, Any]) -> tuple[Any, Any] | None:
    """The registry's range of a port: ``(lo, hi)``, each a number or a tuple with one per value."""
    value = info.get("range")
    if not value:
        return None
    low, high = (tuple(float(v) for v in bound) if isinstance(bound, list | tuple) else float(bound)
                 for bound in value[:2])
    return low, high


def app_from_registry(path: Path, *, owner_uid: int | None = None) -> RunningApp:
    """The app described by one registry file, after the checks of the module doc.

    ``owner_uid``: the uid the app must run as (None: whoever owns the file, provided
    the live supervisor named in it runs as that same uid). Raises
    :class:`SegmentRefused` when the registry is not to be believed, ``FileNotFoundError``
    when it is gone, ``ValueError`` when it is not a registry.
    """
    match = SEGMENT_NAME.fullmatch(path.name)
    if match is None or match.group(4) != "registry.json":
        raise SegmentRefused(f"{shorten(path.name)} is not an rtloop registry name")
    fd = open_in_shm(path.name, os.O_RDONLY, owner_uid=owner_uid, shm_dir=path.parent)
    with os.fdopen(fd, "rb") as file:
        file_uid = os.fstat(file.fileno()).st_uid
        text = file.read(REGISTRY_MAX_BYTES + 1)
    if len(text) > REGISTRY_MAX_BYTES:
        raise ValueError(f"{path.name}: larger than {REGISTRY_MAX_BYTES} bytes; not a registry")
    try:
        registry = json.loads(text)
    except RecursionError:  # anyone may plant a file in /dev/shm: 100 kB of [[[[ must not stop rtloop port
        raise ValueError(f"{path.name}: nested too deeply; not a registry") from None
    if not isinstance(registry, dict) or not isinstance(registry.get("ports"), dict) \
            or not isinstance(registry.get("tasks"), dict):
        raise ValueError(f"{path.name}: not an rtloop registry")
    name, pid = registry.get("app"), registry.get("pid")
    if name != match.group(1) or not isinstance(pid, int) or str(pid) != match.group(2):
        raise SegmentRefused(f"{path.name}: its content names app {shorten(name)} pid {shorten(pid)}, "
                             "its file name another; not used")
    supervisor_uid = process_uid(pid)
    started = registry.get("pid_start_ticks")
    if supervisor_uid is None or not pid_alive(pid) or (started is not None and started != process_start_ticks(pid)):
        raise AppNotRunning(f"{path.name}: supervisor pid {pid} is not running")  # or its pid went to another
    if supervisor_uid != file_uid:
        raise SegmentRefused(f"{path.name} is owned by uid {file_uid}, but its supervisor pid {pid} runs as "
                             f"uid {supervisor_uid}; not used")
    return RunningApp(name, pid, registry, path, file_uid)


@dataclass(frozen=True)
class Refusal:
    """A registry found but not believed (or not ours to act on), and why."""

    path: Path
    app: str
    reason: str
    denied_by_owner: int | None = None
    """The registry's owner when the kernel refused to open it (the caller may not read it)."""


def scan_registries(shm_dir: Path = SHM_DIR, owner_uid: int | None = None) -> tuple[list[RunningApp], list[Refusal]]:
    """Apps whose registry passes the checks (newest first), and the registries refused, with why.

    ``owner_uid``: keep only apps of that uid (others become refusals naming their uid).
    """
    found: list[RunningApp] = []
    refused: list[Refusal] = []
    for path in shm_dir.glob("rtloop-*-registry.json"):
        match = SEGMENT_NAME.fullmatch(path.name)
        claimed = match.group(1) if match else path.name
        try:
            app = app_from_registry(path)
        except (FileNotFoundError, AppNotRunning):
            continue  # removed right now, or its supervisor has ended: stale, not refused
        except SegmentDenied as error:
            if match is not None and not pid_alive(int(match.group(2))):
                continue  # another user's registry left by a supervisor that is gone (its pid is in the name)
            refused.append(Refusal(path, claimed, str(error), error.owner_uid))
            continue
        except (OSError, ValueError, KeyError, TypeError, RtloopError) as error:
            refused.append(Refusal(path, claimed, str(error)))
            continue
        if owner_uid is not None and app.uid != owner_uid:
            refused.append(Refusal(path, app.name, f"app {app.name!r} runs as uid {app.uid}, not uid {owner_uid}"))
            continue
        found.append(app)
    found.sort(key=_mtime, reverse=True)
    return found, refused


def _mtime(app: RunningApp) -> float:
    try:
        return app.path.stat().st_mtime
    except OSError:
        return 0.0


def live_runs_named(name: str, uid: int, shm_dir: Path = SHM_DIR) -> list[RunningApp]:
    """The live real-time runs of app ``name`` by ``uid``, the first registered first (ties: lower pid)."""
    runs = [app for app in scan_registries(shm_dir)[0] if app.name == name and app.uid == uid and app.runs_live]
    return sorted(runs, key=_registered_at)


def _registered_at(app: RunningApp) -> tuple[int, int]:
    try:
        return app.path.stat().st_mtime_ns, app.pid  # written once, when the run registers
    except OSError:
        return 0, app.pid


def running_apps(shm_dir: Path = SHM_DIR, owner_uid: int | None = None) -> list[RunningApp]:
    """Every app whose supervisor is alive and whose registry is believed, newest first."""
    return scan_registries(shm_dir, owner_uid)[0]


def unreachable_app(name: str, refused: list[Refusal], command: str) -> AppNotReachable | None:
    """Why app ``name`` runs but is not for this caller (its registry refused), or None when no
    registry of that name was refused. A permission problem is never reported as "no running
    app": the error says which user to run ``rtloop COMMAND`` as (``port``, ``top``)."""
    why = [r for r in refused if r.app == name]
    if not why:
        return None
    owner, reason = why[0].denied_by_owner, why[0].reason
    if owner == 0:
        return AppNotReachable(f"app {name!r} runs as root: run rtloop {command} as root too "
                               f"({as_root_command(command)} ...); its registry: {reason}")
    if owner is not None:
        return AppNotReachable(f"app {name!r} runs as uid {owner}: run rtloop {command} as that user; "
                               f"its registry: {reason}")
    return AppNotReachable(f"app {name!r}: registry refused: {reason}")


def as_root_command(command: str) -> str:
    """``rtloop COMMAND`` run as root, spelled so that it works from the caller's folder: this clone's
    tools/as-root (``sudo`` outside a clone) and this environment's rtloop (or its Python's ``-m
    rtloop``), each relative to the current folder when inside it, else absolute."""
    try:
        here = Path.cwd()
    except OSError:  # the caller's folder was removed: absolute paths only
        here = Path("/")

    def spelled(path: Path) -> str:
        if here != Path("/") and path.is_relative_to(here):
            return str(path.relative_to(here))
        return str(path)

    as_root = Path(__file__).resolve().parents[3] / "tools" / "as-root"  # src/rtloop/ipc/ → the clone
    program = Path(sys.executable).parent / "rtloop"
    runs_rtloop = spelled(program) if program.is_file() else f"{spelled(Path(sys.executable))} -m rtloop"
    return f"{spelled(as_root) if as_root.is_file() else 'sudo'} {runs_rtloop} {command}"


def connect_app(name: str, timeout_s: float = 0.0, *, owner_uid: int | None = None,
                command: str = "port") -> RunningApp:
    """The running app called ``name`` (an app file's path works too); waits up to ``timeout_s``.

    Only apps run by ``owner_uid`` are considered (default: the caller's own uid). Root
    may name another uid on purpose; any other caller asking for another uid is refused.
    ``command``: the rtloop command asking (``switch``, ``reload``), named in the error of an app
    that runs as another user.
    """
    if name.endswith(".toml") and os.path.isfile(name):
        import tomllib

        try:
            found = tomllib.loads(Path(name).read_text()).get("name", name)
            name = found if isinstance(found, str) else name
        except (OSError, ValueError, RecursionError):
            pass
    me = os.geteuid()
    wanted_uid = me if owner_uid is None else owner_uid
    if wanted_uid != me and me != 0:
        raise AppNotReachable(f"you are uid {me}: only root may act on an app of uid {wanted_uid}")
    deadline = time.monotonic() + timeout_s
    while True:
        apps, refused = scan_registries(SHM_DIR)
        matches = [app for app in apps if app.name == name and app.uid == wanted_uid]
        runs = [app for app in matches if app.runs_live]
        if len(runs or matches) > 1:
            pids = ", ".join(str(app.pid) for app in sorted(runs or matches, key=lambda app: app.pid))
            raise AppNotReachable(f"app {name!r} runs more than once as uid {wanted_uid} (pids {pids}); "
                                  "stop all but one, rtloop will not guess which one you mean")
        if matches:
            return (runs or matches)[0]
        if time.monotonic() >= deadline:
            break
        time.sleep(0.05)
    others = [app for app in apps if app.name == name]
    if others:
        hint = " (as root: rtloop port --user UID)" if me == 0 else " (run as that user, or as root with --user)"
        raise AppNotReachable(f"app {name!r} runs as uid {others[0].uid}, not as uid {wanted_uid}{hint}")
    unreachable = unreachable_app(name, refused, command)
    if unreachable is not None:
        raise unreachable
    running = sorted({app.name for app in apps if app.uid == wanted_uid})
    raise AppNotRunning(f"no running app named {shorten(name)}; running: {running or 'none'}")
