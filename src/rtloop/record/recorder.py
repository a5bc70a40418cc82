"""All of a run's recordings behind one object, shared by ``run`` and ``simulate``.

Statistics stream into fixed-size histograms (:mod:`rtloop.stats.timing_stream`), so the
recorder's memory does not grow with the run. Files: timing.csv and signals.csv always;
run.mcap too when the ``mcap`` packages are installed (``pip install 'rtloop[ros]'``), else
the summary says why it is missing; beside run.mcap, metadata.yaml makes the run
directory a ROS 2 bag (``ros2 bag info``); inputs.csv logs what entered through live
ports (for ``rtloop replay``). ``keep_s=None`` writes everything straight into those
files; ``keep_s=S`` writes segments (of every file that grows with the run, inputs.csv too)
that a :class:`~rtloop.record.flight.FlightWindow` prunes to the last S seconds plus what
surrounds every event, stitched at :meth:`close`.

A recording that fails (disk full, I/O error, folder removed) stops; the run does not:
the statistics go on, and :attr:`Recorder.stopped` says what happened.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rtloop.app.builder import App
from rtloop.app.guards import recorded_input_names
from rtloop.app.sources import file_digest
from rtloop.record.csvfiles import MAX_PENDING_VALUES, InputsCsv, ReadsCsv, SignalsCsv, TimingCsv
from rtloop.record.flight import SEGMENTS_DIR, FlightWindow
from rtloop.record.rosbag2 import bag_contents_of, write_metadata
from rtloop.record.sidecar import sidecar_content, units_by_column, write_sidecar
from rtloop.record.switches import SwitchLog
from rtloop.stats.timing import DEFAULT_TRIM, TaskTiming
from rtloop.stats.timing_stream import StreamingTaskTiming
from rtloop.sudo import invoking_user

if TYPE_CHECKING:  # imported when run.mcap opens: it needs the optional mcap package
    from rtloop.record.mcap_writer import RunMcapWriter

FILE_NAMES = ["timing.csv", "signals.csv", "reads.csv", "inputs.csv", "run.mcap", "snapshots.pkl"]
"""The files of a --keep segment: all that grows with the run (a replay of the window needs the
inputs from its start on: the task snapshots hold the values taken before)."""


class Recorder:
    def __init__(self, app: App, out: Path, *, keep_s: float | None = None, trim: int = DEFAULT_TRIM) -> None:
        out.mkdir(parents=True, exist_ok=True)
        self.out, self.app = out, app
        self.periods_ns = {name: task.config.period_ns for name, task in app.tasks.items()}
        self.statistics = {
            name: StreamingTaskTiming(task.config.period_ns, trim=trim, overrun_policy=task.config.overrun)
            for name, task in app.tasks.items()
        }
        self.last_record: dict[str, tuple[int, int, int, int] | None] = dict.fromkeys(app.tasks)
        """Per task, the newest (cycle, release_ns, start_ns, end_ns) drained."""
        self.keep_s = keep_s
        self.window: FlightWindow | None = None
        self.stopped = ""
        """Why the recording stopped before the run did ('' while it records)."""
        self.mcap_note = ""
        self.t0_ns = 0
        self.latest_ns = 0  # run time (since T0) of the newest release drained
        self.timing: TimingCsv | None = None
        self.signals: SignalsCsv | None = None
        self.mcap: RunMcapWriter | None = None
        self.live: Any = None
        """Also gets what run.mcap gets (``add_rows``, ``add_timing``): the Foxglove live view, if any."""
        self.listeners: list[Any] = []
        """Also hear every drained timing record and stale read (``add_timing``, ``add_reads``)."""
        live_ports = [p for p in app.ports.values() if p.direction == "in"]
        self.inputs: InputsCsv | None = None
        self.sidecar: dict[str, Any] = {}
        """signals.json: units and plots of the recorded signals."""
        # each reader's writers in the order its wiring reads them (TaskWiringPlan.writers)
        self._writers = {name: list(dict.fromkeys(c.source.task for c in app.connections if c.target.task == name))
                         for name in app.tasks}
        self.reads: ReadsCsv | None = None
        self.snapshots: list[Any] = []
        """Task snapshots taken in the current --keep segment (``snapshots.pkl`` beside its files)."""
        self.reads_dropped: dict[str, int] = {}
        """Per task, stale reads its read log could not keep (ring full): replay cannot follow them."""
        self._has_live_ports = bool(live_ports)
        self._port_order = {
            name: [(link.name, link.signal.size) for link in live_ports if link.signal.task == name]
            for name in app.tasks
        }
        self.switches = SwitchLog(app)
        """The controller switches the recorded rows show (tasks of several controllers)."""
        self._guard(self._open_first_files)

    # --- files ---------------------------------------------------------------------------------
    def _path(self, name: str) -> Path:
        return self.window.path(name) if self.window is not None else self.out / name

    def _open_first_files(self) -> None:
        if self.keep_s is not None:
            self.window = FlightWindow(self.out, self.keep_s)
        self.timing = TimingCsv(self._path("timing.csv"))
        if self.app.recorded:
            self.sidecar = sidecar_content(self.app)
            write_sidecar(self.out, self.sidecar)  # small and fixed: beside the files, never rotated
            self.signals = SignalsCsv(
                self._path("signals.csv"), self.app.recorded, self.periods_ns,
                {n: t.runnable.n_outputs for n, t in self.app.tasks.items()},
                {n: (recorded_input_names(self.app, n), t.runnable.output_names) for n, t in self.app.tasks.items()})
        if any(self._writers.values()):  # a stale read needs a connection
            self.reads = ReadsCsv(self._path("reads.csv"))
        if self._has_live_ports:  # a row per value that came in: 1 GB a day from a 1-kHz setpoint topic
            self.inputs = InputsCsv(self._path("inputs.csv"))

    def write_replay_info(self, duration_s: float | None) -> None:
        """``replay.json``: what ``rtloop replay`` needs besides inputs.csv to rebuild the run."""
        source = self.app.source
        if source != "<python>":
            source = str(Path(source).resolve())
        feed_files = {name: str(Path(p.feed).resolve()) for name, p in self.app.ports.items() if p.feed is not None}
        info: dict[str, object] = {"app": self.app.name, "source": source, "duration_s": duration_s,
                                   "feeds": feed_files}
        feeds = {path: file_digest(path) for path in feed_files.values()}
        info["files"] = {**self.app.sources, **{path: digest for path, digest in feeds.items() if digest}}
        self._guard((self.out / "replay.json").write_text, json.dumps(info, indent=1) + "\n")

    def start(self, t0_ns: int, wall_t0_ns: int) -> None:
        """Open run.mcap once the epoch is known (its messages carry wall-clock stamps)."""
        self.t0_ns, self.wall_t0_ns = t0_ns, wall_t0_ns
        self._guard(self._open_mcap)

    def _open_mcap(self) -> None:
        if self.stopped:
            return
        from rtloop.record.mcap_writer import RunMcapWriter

        names = self.signals.names if self.signals is not None else []
        try:
            self.mcap = RunMcapWriter(self._path("run.mcap"), names, self.t0_ns, self.wall_t0_ns,
                                      metadata={"app": self.app.name, "source": self.app.source,
                                                "units": json.dumps(units_by_column(self.sidecar))
                                                if self.sidecar else "{}"},
                                      timing_tasks=list(self.app.tasks))
        except ModuleNotFoundError as error:
            self.mcap_note = f"run.mcap skipped: no module {error.name!r} (pip install 'rtloop[ros]')"

    def _rotate(self) -> None:
        assert self.window is not None
        if self.mcap is not None:
            self.mcap.close()
            self.mcap = None
        self.window.rotate(self.latest_ns, FILE_NAMES)
        if self.timing is not None:
            self.timing.switch_to(self._path("timing.csv"))
        if self.signals is not None:
            self.signals.switch_to(self._path("signals.csv"))
        if self.reads is not None:
            self.reads.switch_to(self._path("reads.csv"))
        if self.inputs is not None:
            self.inputs.switch_to(self._path("inputs.csv"))
        self.snapshots = []
        if not self.mcap_note:
            self._open_mcap()

    def _guard(self, action: Callable[..., object], *args: Any) -> None:
        """Run a file operation; if it fails, stop the recording (never the run)."""
        if self.stopped:
            return
        try:
            action(*args)
        except OSError as error:
            self._stop_recording(error)

    def _stop_recording(self, error: OSError) -> None:
        where = f" ({error.filename})" if error.filename else ""
        what = errno.errorcode.get(error.errno or 0, "error")
        self.stopped = (f"recording stopped at {self.latest_ns / 1e9:.1f} s of run time: "
                        f"{what} {error.strerror or error}{where}; the run went on")
        for writer in (self.mcap, self.timing, self.signals, self.inputs, self.reads):
            if writer is not None:
                with contextlib.suppress(OSError, ValueError):
                    writer.close()
        self.mcap = self.timing = self.signals = self.inputs = self.reads = None

    # --- data ----------------------------------------------------------------------------------
    def add_inputs(self, task: str, ticks: np.ndarray, rows: np.ndarray) -> None:
        """Port values ``task`` took (ticks: ns since T0; rows: [index into the task's input ports, values…])."""
        if self.inputs is not None and len(ticks):
            self._guard(self.inputs.append, task, self.periods_ns[task], self._port_order[task], ticks, rows)

    def add_reads(self, task: str, records: np.ndarray, dropped: int) -> None:
        """Stale reads of ``task`` (read-log records) and how many its ring dropped so far."""
        if dropped:
            self.reads_dropped[task] = dropped
        if len(records):
            for listener in self.listeners:
                listener.add_reads(task, self._writers[task], records)
        if self.reads is not None and len(records):
            self._guard(self.reads.append, task, self.periods_ns[task], self._writers[task], records)

    @property
    def segment_index(self) -> int | None:
        """The --keep segment being written (None: no --keep)."""
        return self.window.current.index if self.window is not None else None

    def add_snapshot(self, snapshot: Any) -> None:
        """A task's state at the start of this --keep segment (the window's replay starts from it)."""
        if self.window is None:
            return
        self.snapshots.append(snapshot)
        self._guard(self._write_snapshots)

    def _write_snapshots(self) -> None:
        import pickle

        path = self._path("snapshots.pkl")
        with open(f"{path}.tmp", "wb") as file:  # readers see the old list or the new one, never half
            pickle.dump(self.snapshots, file)
        os.replace(f"{path}.tmp", path)

    def add_timing(self, task: str, records: np.ndarray) -> None:
        if not len(records):
            return
        self.statistics[task].add(records)
        for listener in self.listeners:  # the misses' causes (runtime/evidence.py:MissWatch)
            listener.add_timing(task, records)
        last = records[-1].tolist()
        self.last_record[task] = (last[0], last[1], last[2], last[3])
        self.latest_ns = max(self.latest_ns, last[1] - self.t0_ns)
        if np.any(records[:, 3] > records[:, 1] + self.periods_ns[task]):
            self.mark_event()
        self._guard(self._write_timing, task, records)

    def _write_timing(self, task: str, records: np.ndarray) -> None:
        if self.timing is not None:
            self.timing.append(task, records)
        if self.mcap is not None:
            self.mcap.add_timing(task, records)
        if self.live is not None:
            self.live.add_timing(task, records)

    def mark_event(self) -> None:
        """Something worth keeping happened now (a miss, a stale read, a fault)."""
        if self.window is not None:
            self.window.mark_event()

    def timing_of(self, task: str) -> TaskTiming:
        """The statistics of ``task`` so far."""
        return self.statistics[task].task_timing()

    def add_signals(self, task: str, ticks: np.ndarray, rows: np.ndarray, lost_so_far: int = 0) -> None:
        """Record-queue rows of ``task``; ``lost_so_far``: rows its queue dropped in all (marked as gaps)."""
        self.switches.add(task, ticks, rows)
        if self.signals is not None:
            self.signals.add(task, ticks, rows, lost_so_far)

    def signal_room(self, task: str) -> int:
        """How many rows of ``task`` the recorder takes now: past signals.csv's bound they wait in the
        task's record queue (and what overflows it is counted lost: a gap, not memory)."""
        return self.signals.room(task) if self.signals is not None else MAX_PENDING_VALUES

    def signals_lost_at_end(self, task: str, count: int) -> None:
        """``count`` rows of ``task`` came after the newest one drained and will never be: a gap in signals.csv."""
        if self.signals is not None:
            self.signals.lost_after_newest(task, count)

    def flush(self, final: bool = False) -> None:
        self._guard(self._flush, final)

    def _flush(self, final: bool) -> None:
        if self.timing is not None:
            self.timing.flush()
        if self.inputs is not None:
            self.inputs.flush()
        if self.reads is not None:
            self.reads.flush()
        if self.signals is not None:
            times, rows = self.signals.flush(final=final)
            if self.mcap is not None and len(times):
                self.mcap.add_rows(times, rows)
            if self.live is not None and len(times):
                self.live.add_rows(times, rows)
        if self.window is not None and not final and self.window.due(self.latest_ns):
            self._rotate()

    def close(self) -> None:
        self.flush(final=True)
        self._guard(self._close_files)
        if self.window is not None:
            try:
                self.window.stitch(self.out, FILE_NAMES)
            except Exception as error:  # a full disk, or mcap's own errors on a damaged segment
                reason = error.strerror if isinstance(error, OSError) else error
                problem = f"the kept segments could not be joined ({reason}); they are in {SEGMENTS_DIR}/"
                self.stopped = f"{self.stopped}; {problem}" if self.stopped else problem
        self._guard(self._write_bag_metadata)
        give_to_invoking_user(self.out)

    def _close_files(self) -> None:
        for writer in (self.timing, self.signals, self.mcap, self.inputs, self.reads):
            if writer is not None:
                writer.close()

    def _write_bag_metadata(self) -> None:
        """metadata.yaml beside the final run.mcap (read back from it when segments were joined)."""
        if self.mcap_note or self.stopped or not (self.out / "run.mcap").exists():
            return
        if self.window is None and self.mcap is not None:
            write_metadata(self.out, self.mcap.bag_contents())
        else:
            write_metadata(self.out, bag_contents_of(self.out / "run.mcap"))

    def to_json(self) -> dict[str, object]:
        """What the summary says about the recording."""
        window = self.window.to_json() if self.window is not None else {}
        dropped = {"reads_dropped": dict(self.reads_dropped)} if self.reads_dropped else {}
        return {"keep_s": self.keep_s, "stopped": self.stopped or None, **window, **dropped}


def give_to_invoking_user(out: Path) -> None:
    """Under sudo, hand the artifacts (a folder and what is in it, or one file) to the user who ran
    sudo, so they can open and report them."""
    invoker = invoking_user()
    if invoker is None:
        return
    uid, gid = invoker
    try:
        paths = [out, *out.iterdir()]
    except NotADirectoryError:
        paths = [out]  # a file of its own (a sweep's table)
    except OSError:
        return
    for path in paths:
        try:
            # a link planted in the folder is handed over itself; what it points to is never touched
            os.chown(path, uid, gid, follow_symlinks=False)
        except OSError:
            pass
