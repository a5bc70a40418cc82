"""All of a run's recordings behind one object, shared by ``run`` and ``simulate``.

timing.csv and signals.csv are always written; run.mcap too when the ``mcap`` packages
are installed (``pip install 'rtloop[ros]'``), else the summary says why it is missing.
Beside run.mcap, metadata.yaml makes the run directory a ROS 2 bag (``ros2 bag info``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.app.builder import App
from rtloop.record.csvfiles import InputsCsv, SignalsCsv, TimingCsv
from rtloop.record.rosbag2 import write_metadata
from rtloop.timing import TimingSamples


class Recorder:
    def __init__(self, app: App, out: Path) -> None:
        out.mkdir(parents=True, exist_ok=True)
        self.out = out
        self.timing = TimingCsv(out / "timing.csv")
        self.signals = (
            SignalsCsv(out / "signals.csv", app.recorded,
                       {n: t.config.period_ns for n, t in app.tasks.items()},
                       {n: t.runnable.n_outputs for n, t in app.tasks.items()},
                       {n: (t.runnable.input_names, t.runnable.output_names) for n, t in app.tasks.items()})
            if app.recorded else None
        )
        live_ports = [p for p in app.ports.values() if p.direction == "in"]
        self.inputs = InputsCsv(out / "inputs.csv") if live_ports else None
        self._port_order = {
            name: [(link.name, link.signal.size) for link in live_ports if link.signal.task == name]
            for name in app.tasks
        }
        self.mcap = None
        self.mcap_note = ""
        self.live: Any = None
        """Also gets what run.mcap gets (``add_rows``, ``add_timing``): the Foxglove live view, if any."""
        self.app = app
        self._timing_records: dict[str, list[np.ndarray]] = {name: [] for name in app.tasks}

    def start(self, t0_ns: int, wall_t0_ns: int) -> None:
        """Open run.mcap once the epoch is known (its messages carry wall-clock stamps)."""
        from rtloop.record.mcap_writer import RunMcapWriter

        names = self.signals.names if self.signals is not None else []
        try:
            self.mcap = RunMcapWriter(self.out / "run.mcap", names, t0_ns, wall_t0_ns,
                                      metadata={"app": self.app.name, "source": self.app.source})
        except ModuleNotFoundError as error:
            self.mcap_note = f"run.mcap skipped: no module {error.name!r} (pip install 'rtloop[ros]')"

    def write_replay_info(self, duration_s: float) -> None:
        """``replay.json``: what ``rtloop replay`` needs besides inputs.csv to rebuild the run."""
        import json

        source = self.app.source
        if source != "<python>":
            source = str(Path(source).resolve())
        info = {
            "app": self.app.name, "source": source, "duration_s": duration_s,
            "feeds": {name: str(Path(p.feed).resolve()) for name, p in self.app.ports.items() if p.feed is not None},
        }
        (self.out / "replay.json").write_text(json.dumps(info, indent=1) + "\n")

    def add_inputs(self, task: str, ticks: np.ndarray, rows: np.ndarray) -> None:
        """Port values ``task`` took (ticks: ns since T0; rows: [index into the task's input ports, values…])."""
        if self.inputs is not None and len(ticks):
            self.inputs.append(task, self.app.tasks[task].config.period_ns, self._port_order[task], ticks, rows)

    def add_timing(self, task: str, records: np.ndarray) -> None:
        if len(records):
            self._timing_records[task].append(records)
            self.timing.append(task, records)
            if self.mcap is not None:
                self.mcap.add_timing(task, records)
            if self.live is not None:
                self.live.add_timing(task, records)

    def samples(self, task: str) -> TimingSamples:
        """Every timing record of ``task`` added so far (for the statistics)."""
        records = self._timing_records[task]
        return TimingSamples.from_records(np.concatenate(records) if records else np.empty((0, 4), np.int64))

    def add_signals(self, task: str, ticks: np.ndarray, rows: np.ndarray) -> None:
        if self.signals is not None:
            self.signals.add(task, ticks, rows)

    def flush(self, final: bool = False) -> None:
        self.timing.flush()
        if self.inputs is not None:
            self.inputs.flush()
        if self.signals is not None:
            times, rows = self.signals.flush(final=final)
            if self.mcap is not None and times:
                self.mcap.add_rows(np.array(times, dtype=np.int64), np.array(rows, dtype=np.float64))
            if self.live is not None and times:
                self.live.add_rows(np.array(times, dtype=np.int64), np.array(rows, dtype=np.float64))

    def close(self) -> None:
        self.flush(final=True)
        self.timing.close()
        if self.inputs is not None:
            self.inputs.close()
        if self.signals is not None:
            self.signals.close()  # its last rows were flushed just above
        if self.mcap is not None:
            self.mcap.close()
            write_metadata(self.out, self.mcap.bag_contents())
        give_to_invoking_user(self.out)


def give_to_invoking_user(out: Path) -> None:
    """Under sudo, hand the artifacts to the user who ran sudo, so they can open and report them."""
    uid, gid = os.environ.get("SUDO_UID"), os.environ.get("SUDO_GID")
    if os.geteuid() != 0 or not uid or not gid:
        return
    for path in [out, *out.iterdir()]:
        try:
            # a link planted in the folder is handed over itself; what it points to is never touched
            os.chown(path, int(uid), int(gid), follow_symlinks=False)
        except OSError:
            pass
