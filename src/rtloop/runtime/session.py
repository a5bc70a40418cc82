"""One run session: the output folder, shared memory, recorder and summary of a run, and their cleanup.

``run``, ``simulate`` and ``replay`` all enter a :class:`RunSession` (a context manager, like
a trio nursery: whatever it opens, it closes on every way out). It owns

- the output folder, under the rule that protects what earlier runs recorded: a folder that
  already holds a run is never written into unless the caller asks (``force=True``,
  ``--force``), and then the earlier run's files are removed first, so no stale
  ``report.html`` or ``report-figures/`` sits beside new data. Two things are refused even
  then: writing into the run a replay reads (or a folder inside it), and a ``segments/``
  folder left by a run that did not finish (its only recording);
- the shared memory (:class:`~rtloop.runtime.layout.AppLayout`), the recorder and
  ``summary.json``, and the drain that moves what tasks recorded into the recorder, in a
  time budget so the caller's control loop always gets the processor back;
- the counts of what was lost on the way (timing records, signal rows, logged inputs), for
  the summary's notes;
- the cleanup: the recorder closed, the final summary written (a second Ctrl-C waits until
  it is), the reserve file given back, every segment removed and closed here
  (descriptors and mappings: a library's caller runs many apps in one process).

The supervisor (``runtime/supervisor.py``) keeps only the processes' lifecycle; the
simulator only its logical clock.
"""

from __future__ import annotations

import contextlib
import enum
import errno
import fcntl
import os
import shutil
import signal
import stat
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from rtloop.app.builder import App
from rtloop.app.specs import WATCHDOG_MIN_S, check_duration
from rtloop.errors import AppError
from rtloop.ipc.status import ControlWord
from rtloop.linux.memory import give_back_free_heap
from rtloop.owners import output_folder_problem
from rtloop.record.disk_room import check_room
from rtloop.record.recorder import Recorder, give_to_invoking_user
from rtloop.record.summary import SUMMARY_RESERVE_BYTES, RunSummary, SummaryFile
from rtloop.runtime.layout import AppLayout, TaskHandles
from rtloop.switching import keep_start_code, prepare_reloads

RUN_FILES = ("summary.json", "timing.csv", "signals.csv", "signals.json", "run.mcap", "metadata.yaml",
             "inputs.csv", "reads.csv", "replay.json", "report.html")
"""Files a run (and ``rtloop report``) writes into its folder."""
LEFTOVERS = (".summary-reserve", ".summary.json.tmp", ".signals.json.tmp")
"""Files of a run that are not its data (a reserve, a half-written temporary): removed, never a reason to refuse."""
RUN_FOLDERS = ("report-figures", "snapshots")
"""Folders of a finished run, removed with it by ``force``: its report's figures and a ``--keep`` run's task
snapshots (``runtime/snapshot.py``)."""
CODE_FOLDER = "code"
"""The controllers' code a run kept (``switching.keep_start_code``, ``rtloop reload``): removed with the run it
belongs to by ``force`` (left behind, it kept its owner: a run as root into a user's earlier run folder refused
every ``rtloop reload``, ``code is not a folder of yours``), but alone it is no run: a simulation's reload
profile finds the code it loads there, put in before the simulation."""
UNFINISHED_FOLDER = "segments"
"""The flight recorder's folder: present after a run only when the run did not finish."""


class RunDirectoryError(AppError):
    """The output folder holds a run that would be overwritten, or is the run being replayed."""


def prepare_out_dir(out: Path, *, force: bool = False, protect: Iterable[Path] = ()) -> Path:
    """Make ``out`` ready for a new run's artifacts, or refuse before anything is written.

    ``protect``: folders whose contents must survive (the run a replay reads): ``out`` may be
    neither one of them nor inside one. Returns ``out``. A folder that cannot be made or
    cleared (``/proc/x``, a file's path, a folder of another user) is a :class:`RunDirectoryError`
    naming the path and the reason.
    """
    with _out_dir_errors(out):
        return _prepare_out_dir(out, force=force, protect=protect)


@contextlib.contextmanager
def _out_dir_errors(out: Path) -> Iterator[None]:
    try:
        yield
    except OSError as error:
        raise RunDirectoryError(f"--out {out} cannot be used: {_os_reason(error, out)}; nothing was run: "
                                "choose another --out") from None


def _os_reason(error: OSError, out: Path) -> str:
    """Why an OSError happened, with the path it happened at when that is not ``out`` itself."""
    reason = error.strerror or str(error)
    where = error.filename
    if where is not None and Path(os.fsdecode(where)) != out:
        reason = f"{reason} ({os.fsdecode(where)})"
    return reason


def _prepare_out_dir(out: Path, *, force: bool, protect: Iterable[Path]) -> Path:
    _check_out_dir(out, protect)
    if not out.exists():
        missing = [folder for folder in (out, *out.parents) if not folder.exists()]
        out.mkdir(parents=True)
        for folder in reversed(missing):  # under sudo, `runs/` stays the user's to write in
            folder.chmod(folder.stat().st_mode & ~0o022)  # whatever the umask: nobody else writes in it
            give_to_invoking_user(folder)
        return out
    for name in LEFTOVERS:
        if os.path.lexists(out / name):
            _remove(out / name)
    found = [name for name in (*RUN_FILES, *RUN_FOLDERS) if os.path.lexists(out / name)]
    if not found:
        return out
    if not force:
        raise RunDirectoryError(f"{out} already holds a run ({', '.join(found[:3])}); nothing was written: "
                                "choose another --out, or add --force to replace it (force=True in Python)")
    for name in (*found, CODE_FOLDER):
        if os.path.lexists(out / name):
            _remove(out / name)
    return out


def lock_out_dir(out: Path) -> int:
    """Hold ``out`` for this run (an exclusive ``flock`` on the folder, released when the process
    ends, however it ends): a second run into the same folder, even with ``force``, is refused
    while this one goes on, so it can neither delete a live run's files nor mix its own in."""
    fd = os.open(out, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise RunDirectoryError(f"--out {out} is the folder of a run still going (another rtloop holds it); "
                                "nothing was written, --force or not: stop that run first, or choose another "
                                "--out") from None
    except OSError:
        os.close(fd)
        raise
    return fd


def _locked(out: Path) -> int:
    with _out_dir_errors(out):
        return lock_out_dir(out)


def check_out_dir(out: Path, *, protect: Iterable[Path] = ()) -> None:
    """The refusals that hold even with ``force`` (see :func:`prepare_out_dir`); writes nothing."""
    with _out_dir_errors(out):
        _check_out_dir(out, protect)


def _check_out_dir(out: Path, protect: Iterable[Path]) -> None:
    resolved = out.resolve()
    for kept in protect:
        kept_resolved = Path(kept).resolve()
        if resolved == kept_resolved or kept_resolved in resolved.parents:
            raise RunDirectoryError(f"--out {out} is the run {kept} it replays, or inside it; the replay would "
                                    "overwrite what it compares with: choose another folder")
    if out.exists() and not out.is_dir():
        raise RunDirectoryError(f"--out {out} exists and is not a folder")
    problem = output_folder_problem(out)
    if problem is not None:
        raise RunDirectoryError(f"--out {out}: {problem}; nothing was run: choose a folder of yours")
    if os.path.lexists(out / UNFINISHED_FOLDER):
        raise RunDirectoryError(f"{out}/{UNFINISHED_FOLDER}/ holds the recording of a run that did not finish; "
                                "nothing was written: move it away (or choose another --out); --force "
                                "never deletes it")


def reserve_summary(out: Path, *, made_here: bool) -> SummaryFile:
    """The summary file with its disk space reserved, or a refusal before the run starts.

    Without the reserve the summary of a run that fills the disk could not be written (an
    empty summary.json, a run that says nothing of itself): such a run is refused, and the
    folder is removed again if it was made for it and is still empty.
    """
    try:
        return SummaryFile(out)  # reserves its disk space first
    except OSError as error:
        if made_here:
            with contextlib.suppress(OSError):
                out.rmdir()
        if error.errno in (errno.ENOSPC, errno.EDQUOT):
            raise RunDirectoryError(f"no space at {out}: {free_bytes(out)} bytes free, a run needs "
                                    f"{SUMMARY_RESERVE_BYTES} for its summary; nothing was run: free some "
                                    "space or choose another --out") from None
        raise RunDirectoryError(f"--out {out}: cannot write there: {_os_reason(error, out)}; nothing was run: "
                                "choose another --out") from None


def free_bytes(folder: Path) -> int:
    """Bytes an unprivileged writer may still use on ``folder``'s file system (0 if unknown)."""
    for path in (folder, *folder.parents):
        with contextlib.suppress(OSError):
            stats = os.statvfs(path)
            return stats.f_bavail * stats.f_frsize
    return 0


def _remove(path: Path) -> None:
    """Remove a file, a link (never what it points to) or a folder of the earlier run."""
    if stat.S_ISDIR(os.lstat(path).st_mode):
        shutil.rmtree(path)
    else:
        path.unlink()


# --- the session ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Limits:
    """Every time limit of a run's lifecycle, in one place (tests shrink them to run faster)."""

    startup_allowance_s: float = 30.0
    """Time to start a task process (Python, numpy, the runnable's imports) on top of the run's duration."""
    stop_grace_s: float = 5.0
    """Time (plus one period) a task has to stop after the stop request before it is killed."""
    watchdog_grace_s: float = 2.0
    """Between SIGTERM and SIGKILL of a task the watchdog found stuck."""
    watchdog_min_s: float = WATCHDOG_MIN_S
    """The watchdog never calls a task stuck sooner than this (a loaded machine stalls for seconds)."""
    drain_interval_s: float = 0.05
    """Sleep of the supervisor's control loop between two drains."""
    drain_budget_s: float = 0.025
    """Most time one drain may take before the control loop (signals, watchdog, summary) comes back."""
    stop_drain_budget_s: float = 0.3
    """Most time the drain after the tasks stopped may take; what is still waiting then is counted
    as lost, never written (a supervisor that fell behind must not make Ctrl-C wait for its backlog)."""
    summary_interval_s: float = 2.0
    """How often summary.json is rewritten during a run."""
    start_margin_ns: int = 100_000_000
    """T0 lies this far after the moment every task is ready."""


DEFAULT_LIMITS = Limits()

STARTUP_ALLOWANCE_ENV = "RTLOOP_STARTUP_ALLOWANCE_S"  # more where start-up is slow: emulation, a small board


def startup_allowance_s(default_s: float) -> float:
    """``default_s``, or the seconds RTLOOP_STARTUP_ALLOWANCE_S gives (1 to 3600)."""
    text = os.environ.get(STARTUP_ALLOWANCE_ENV)
    if text is None:
        return default_s
    try:
        seconds = float(text)
    except ValueError:
        seconds = float("nan")
    if not 1 <= seconds <= 3600:  # also NaN
        raise AppError(f"{STARTUP_ALLOWANCE_ENV}={text!r}: a number of seconds from 1 to 3600 is expected")
    return seconds


class RunState(enum.Enum):
    """Where a run is; once it leaves RUNNING, why it ended (``stopped_by`` in summary.json)."""

    RUNNING = "running"
    DURATION = "duration"
    """Its duration ran out (or, for a run without one, never set: it was stopped otherwise)."""
    SIGNAL = "signal"
    """Ctrl-C or SIGTERM."""
    FAULT = "fault"
    """A task raised, died or would not stop."""
    WATCHDOG = "watchdog"
    """A task stopped making progress."""
    REQUESTED = "requested"
    """A runnable raised StopRequested (the summary names the task, the cycle and the reason)."""


DRAIN_BATCH_RECORDS = 4096


@dataclass
class Losses:
    """What did not reach the recording, per task: counted by the shared-memory queues, and
    what was still waiting in them when the drain after the stop ran out of time."""

    timing: dict[str, int]
    signal_rows: dict[str, int]
    inputs: dict[str, int]
    timing_at_stop: dict[str, int] = field(default_factory=dict)
    signal_rows_at_stop: dict[str, int] = field(default_factory=dict)

    def total(self) -> int:
        return sum(sum(counts.values()) for counts in (self.timing, self.signal_rows, self.inputs,
                                                        self.timing_at_stop, self.signal_rows_at_stop))

    def to_json(self) -> dict[str, dict[str, dict[str, int]]]:
        """summary.json's ``recording.lost`` (per kind, per task, only where something was lost):
        the queues' drops during the run, and (``*_at_stop``) what was left unwritten at the end."""
        kinds = {"timing_records": self.timing, "signal_rows": self.signal_rows, "inputs": self.inputs,
                 "timing_records_at_stop": self.timing_at_stop, "signal_rows_at_stop": self.signal_rows_at_stop}
        return {"lost": {kind: {t: n for t, n in counts.items() if n} for kind, counts in kinds.items()}}

    def notes(self) -> list[str]:
        lines = []
        for task in dict.fromkeys([*self.timing_at_stop, *self.signal_rows_at_stop]):
            timing, rows = self.timing_at_stop.get(task, 0), self.signal_rows_at_stop.get(task, 0)
            if timing or rows:
                lines.append(f"task {task}: {timing} timing records and {rows} signal rows not written: still "
                             "waiting when the time to record after the stop ran out (the supervisor had fallen "
                             "behind); timing.csv and signals.csv end early, signals.csv marks the gap")
        for task, count in self.timing.items():
            if count:
                lines.append(f"task {task}: {count} timing records lost (its timing ring was full: the supervisor "
                             "fell behind); timing.csv lacks those cycles, they are not counted as overruns")
        for task, count in self.signal_rows.items():
            if count:
                lines.append(f"task {task}: {count} signal rows lost (its record queue was full: the supervisor "
                             "fell behind); signals.csv leaves those cells empty")
        for task, count in self.inputs.items():
            if count:
                lines.append(f"task {task}: {count} port values taken but not logged (its input log was full); "
                             "a replay of this run will not see them")
        return lines


class RunSession:
    """The resources of one run (see the module's docstring); enter it with ``with``.

    ``summarise(running)`` builds the summary (the caller knows its tasks); the session writes
    it every ``summary_interval_s`` through :meth:`write_summary_if_due` and at the end.
    """

    def __init__(self, app: App, out: str | Path, *, mode: str, duration_s: float | None, keep_s: float | None,
                 trim: int, force: bool = False, protect: Iterable[Path] = (), limits: Limits = DEFAULT_LIMITS,
                 registry: bool = True, check_disk: bool = True) -> None:
        app.validate()
        if duration_s is not None:
            check_duration(duration_s)
        if keep_s is not None and not keep_s > 0:
            raise AppError(f"--keep must be > 0 seconds, got {keep_s}")
        if isinstance(trim, bool) or not isinstance(trim, int) or trim < 0:
            raise AppError(f"--trim must be a whole number of cycles ≥ 0, got {trim!r}")
        self.app, self.out, self.mode = app, Path(out), mode
        self.duration_s, self.keep_s, self.trim, self.force = duration_s, keep_s, trim, force
        self.protect = tuple(Path(p) for p in protect)
        self.limits = limits
        self.registry = registry
        self.check_disk = check_disk
        """Refuse, before anything is written, a recording of the whole duration that would not fit."""
        self.state = RunState.RUNNING
        self.summarise: Callable[[bool], RunSummary] | None = None
        self.summary: RunSummary | None = None
        self.layout: AppLayout
        self.recorder: Recorder
        self.summary_file: SummaryFile
        self._opened: list[str] = []
        self._next_summary_s = 0.0
        self.losses = Losses({}, {}, {})
        self._next_task = 0  # the task the next drain serves first
        self._timing_drained: dict[str, int] = {}  # per task, timing records taken from its ring
        self._lock_fd = -1
        """The folder's lock (:func:`lock_out_dir`), held for the run's life."""
        self.before_close: list[Callable[[], None]] = []
        """Called before the shared memory is removed (the simulator lets go of its views)."""

    # --- opening -------------------------------------------------------------------------------
    def __enter__(self) -> RunSession:
        check_out_dir(self.out, protect=self.protect)  # refusals first: nothing is written yet
        if self.check_disk and self.duration_s is not None and self.keep_s is None:
            check_room(self.app, self.out, self.duration_s)  # everything kept: it must fit on the disk
        summary_path = self.out / "summary.json"
        # The layout checks memory and loads profiles: bad input is refused before the folder is touched.
        self.layout = AppLayout.create(self.app, summary_path if self.registry else None, self.mode)
        for spec in self.app.tasks.values():  # where `rtloop reload` keeps code; simulate waits for it
            prepare_reloads(spec.runnable, self.out / "code", wait=self.mode != "run")
        self._opened.append("layout")
        existed = self.out.exists()
        try:
            if existed:  # held before --force removes anything in it
                self._lock_fd = _locked(self.out)
            prepare_out_dir(self.out, force=self.force, protect=self.protect)
            if not existed:
                self._lock_fd = _locked(self.out)
            self.summary_file = reserve_summary(self.out, made_here=not existed)
            self._opened.append("summary")
            self.recorder = Recorder(self.app, self.out, keep_s=self.keep_s, trim=self.trim)
            keep_start_code({name: spec.runnable for name, spec in self.app.tasks.items()}, self.out / "code")
            self._opened.append("recorder")
            self.recorder.write_replay_info(self.duration_s)
        except BaseException:
            self._close_resources()
            raise
        return self

    def __exit__(self, *_exc: object) -> None:
        with signals_deferred():  # a second Ctrl-C must not cost summary.json and metadata.yaml
            try:
                self._finish()
            finally:
                self._close_resources()
        if self.summary_file_problem:
            import sys

            sys.stderr.write(f"rtloop: {self.summary_file_problem}\n")

    @property
    def summary_file_problem(self) -> str:
        return self.summary_file.problem if "summary" in self._opened else ""

    def _finish(self) -> None:
        if "recorder" not in self._opened:
            return
        try:
            self.recorder.close()

        except Exception as error:  # the recording's own failure is reported, never raised over the run's
            self.recorder.stopped = self.recorder.stopped or f"recording not closed: {error}"
        if self.summarise is not None:
            self.summary = self.summarise(False)
            self.summary_file.write(self.summary)
            give_to_invoking_user(self.out)  # the last summary.json is a new file (written, then renamed)

    def _close_resources(self) -> None:
        if self._lock_fd >= 0:  # after the last summary: the folder is another run's to take
            os.close(self._lock_fd)
            self._lock_fd = -1
        hooks, self.before_close = self.before_close, []
        for hook in hooks:
            with contextlib.suppress(Exception):
                hook()
        if "summary" in self._opened:
            self.summary_file.close()
        if "layout" in self._opened:
            self._opened.remove("layout")  # stop_tasks no longer touches the control block
            self.layout.close()
        self._opened.clear()

    # --- during the run -----------------------------------------------------------------------
    def stop_tasks(self) -> None:
        """Ask every task to stop at its next release (one word in shared memory: safe in a signal handler)."""
        if "layout" in self._opened:
            self.layout.control[ControlWord.STOP] = 1

    def write_summary_if_due(self) -> None:
        now_s = time.monotonic()
        if self.summarise is None or now_s < self._next_summary_s:
            return
        self._next_summary_s = now_s + self.limits.summary_interval_s
        self.summary_file.write(self.summarise(True), durable=False)  # the final one is synced
        give_back_free_heap()  # what the drains freed: the supervisor's resident size stays what it uses

    def drain(self, budget_s: float | None = None) -> bool:
        """Move what the tasks recorded into the recorder, in batches, for at most ``budget_s``.

        Returns whether records were left waiting (the caller comes back soon). ``None``: drain
        everything (at the end, when the tasks have stopped). The budget is what keeps a
        supervisor that cannot keep up serving Ctrl-C, the watchdog and the summary: what it
        cannot take is dropped by the full queues, counted, and reported. It is looked at after
        each task's batch, and the next drain starts with the task after the last one served,
        so a short budget serves every task in turn.
        """
        deadline = None if budget_s is None else time.monotonic() + budget_s
        tasks = list(self.layout.tasks.items())
        try:
            while True:
                more = False
                for _ in range(len(tasks)):
                    name, handles = tasks[self._next_task]
                    self._next_task = (self._next_task + 1) % len(tasks)
                    more |= self._drain_task(name, handles)
                    if more and deadline is not None and time.monotonic() >= deadline:
                        return True
                if not more:
                    return False
                self.recorder.flush()  # the rows of each round written: memory stays bounded
        finally:
            self.recorder.flush()
            self._count_losses()

    def _drain_task(self, name: str, handles: TaskHandles) -> bool:
        """One batch of ``name``'s records into the recorder; returns whether more are waiting."""
        recorder = self.recorder
        records = handles.timing.drain(DRAIN_BATCH_RECORDS)
        self._timing_drained[name] = self._timing_drained.get(name, 0) + len(records)
        recorder.add_timing(name, records)
        more = len(records) == DRAIN_BATCH_RECORDS
        if handles.input_log is not None:
            recorder.add_inputs(name, *handles.input_log.drain())
        if handles.read_log is not None:
            recorder.add_reads(name, handles.read_log.drain(), handles.read_log.dropped)
        if handles.record is not None:
            ticks, rows = handles.record.drain(min(DRAIN_BATCH_RECORDS, recorder.signal_room(name)))
            recorder.add_signals(name, ticks, rows, lost_so_far=handles.record.dropped)
            more |= len(ticks) == DRAIN_BATCH_RECORDS
        return more

    def drain_after_stop(self, budget_s: float) -> None:
        """The last drain of a run whose tasks have stopped, for at most ``budget_s``.

        What is still waiting then is not written: it is counted (``recording.lost.*_at_stop``
        and a note in summary.json), and signals.csv marks a gap where its rows would be.
        """
        if not self.drain(budget_s):
            return
        for name, handles in self.layout.tasks.items():
            timing_left = handles.timing.written_total - self._timing_drained.get(name, 0)
            rows_left = handles.record.sent - handles.record.received if handles.record is not None else 0
            if timing_left > 0:
                self.losses.timing_at_stop[name] = timing_left
            if rows_left > 0:
                self.losses.signal_rows_at_stop[name] = rows_left
                self.recorder.signals_lost_at_end(name, rows_left)

    def _count_losses(self) -> None:
        for name, handles in self.layout.tasks.items():
            self.losses.timing[name] = handles.timing.dropped
            if handles.record is not None:
                self.losses.signal_rows[name] = handles.record.dropped
            if handles.input_log is not None:
                self.losses.inputs[name] = handles.input_log.dropped

    def notes(self, *more: str) -> list[str]:
        """The summary's notes: the recording's, what was lost, and ``more``."""
        recorder = self.recorder
        return [note for note in (recorder.mcap_note, *more, recorder.stopped, *self.losses.notes()) if note]


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""What stops a run the orderly way: Ctrl-C, ``kill``/systemd, a terminal (an SSH connection) that closes."""


def drop_output_to_a_lost_terminal(signum: int) -> None:
    """After SIGHUP the terminal is gone and a write to it fails (EIO) in the middle of the orderly
    stop: console lines to a terminal go to /dev/null from now on (a file or a pipe keeps them)."""
    if signum != signal.SIGHUP:
        return
    devnull = os.open(os.devnull, os.O_WRONLY | os.O_CLOEXEC)
    try:
        for fd in (1, 2):
            with contextlib.suppress(OSError):
                if stat.S_ISCHR(os.fstat(fd).st_mode):  # a hung-up tty no longer says it is one (isatty)
                    os.dup2(devnull, fd, inheritable=True)
    finally:
        os.close(devnull)


@contextlib.contextmanager
def stop_signals_handled(on_stop: Callable[[int], None]) -> Iterator[None]:
    """In the block (a run), SIGINT/SIGTERM/SIGHUP call ``on_stop(signum)``; the handlers before come back after.
    Only the main thread can set handlers: elsewhere (a library's caller in a thread) nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, _frame: object) -> None:
        drop_output_to_a_lost_terminal(signum)
        on_stop(signum)

    previous = {s: signal.signal(s, handler) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for signum, before in previous.items():
            signal.signal(signum, before)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold SIGINT/SIGTERM/SIGHUP back while the block runs; then act on them as the handlers before would."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    def defer(signum: int, _frame: object) -> None:
        drop_output_to_a_lost_terminal(signum)  # now: the block may print
        caught.append(signum)

    previous = {s: signal.signal(s, defer) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for which, handler in previous.items():
            signal.signal(which, handler)
        for signum in caught:
            handler = previous[signal.Signals(signum)]
            if callable(handler):
                handler(signum, None)
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), signum)
