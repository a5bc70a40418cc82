"""``timing.csv`` and ``signals.csv``, written as data arrives (nothing waits for the end).

timing.csv  ``task,cycle,release_ns,start_ns,end_ns``, one row per cycle, appended and
            flushed at every drain, so a crash loses at most the last drain interval.
signals.csv ``t_s`` then one column per recorded signal. Row k holds tick k's release
            time and the values that tick computed; with several periods, rows are the
            union of release times and a slower task's columns hold their last value.
"""

from __future__ import annotations

import heapq
from pathlib import Path
from typing import TextIO

import numpy as np

from rtloop.app.builder import SignalRef


class TimingCsv:
    HEADER = "task,cycle,release_ns,start_ns,end_ns\n"

    def __init__(self, path: Path) -> None:
        self.file: TextIO = self._open(path)

    def _open(self, path: Path) -> TextIO:
        file = open(path, "w", buffering=1 << 16)  # noqa: SIM115
        file.write(self.HEADER)
        return file

    def switch_to(self, path: Path) -> None:
        """Go on in a new file (a recording segment), which starts with the header."""
        self.file.close()
        self.file = self._open(path)

    def append(self, task: str, records: np.ndarray) -> None:
        if len(records):
            lines = [f"{task},{c},{r},{s},{e}\n" for c, r, s, e in records.tolist()]
            self.file.writelines(lines)

    def flush(self) -> None:
        self.file.flush()

    def close(self) -> None:
        self.file.close()


class SignalsCsv:
    """Collects record-queue rows per task and writes signals.csv rows in time order.

    Rows are written once every recorded task has delivered the ticks up to that
    time, so the file grows during the run.
    """

    def __init__(
        self,
        path: Path,
        recorded: list[SignalRef],
        periods_ns: dict[str, int],
        n_outputs: dict[str, int],
    ) -> None:
        self.path = path
        self.columns: list[tuple[str, int]] = []  # (task, index into the record row)
        names: list[str] = []
        for ref in recorded:
            offset = 0 if ref.side == "y" else n_outputs[ref.task]
            for i, name in zip(range(ref.start, ref.stop), ref.names(), strict=True):
                self.columns.append((ref.task, offset + i))
                names.append(name)
        self.names = names
        self.tasks = sorted({task for task, _ in self.columns})
        self.periods_ns = periods_ns
        self.pending: dict[str, list[tuple[int, np.ndarray]]] = {t: [] for t in self.tasks}
        self.delivered_ns: dict[str, int] = dict.fromkeys(self.tasks, -1)
        self.held: dict[str, np.ndarray | None] = dict.fromkeys(self.tasks)
        self.rows_written = 0
        self.file: TextIO = self._open(path)

    def _open(self, path: Path) -> TextIO:
        file = open(path, "w", buffering=1 << 16)  # noqa: SIM115
        file.write(",".join(["t_s", *self.names]) + "\n")
        return file

    def switch_to(self, path: Path) -> None:
        """Go on in a new file (a recording segment); the rows still pending go there."""
        self.file.close()
        self.path, self.file = path, self._open(path)

    def add(self, task: str, ticks: np.ndarray, rows: np.ndarray) -> None:
        if task not in self.pending or not len(ticks):
            return
        period = self.periods_ns[task]
        self.pending[task].extend(zip((ticks * period).tolist(), rows, strict=True))
        self.delivered_ns[task] = int(ticks[-1]) * period

    def flush(self, final: bool = False) -> tuple[list[int], list[list[float]]]:
        """Write every row whose time all recorded tasks have reached; return those rows.

        Returns (times since T0 in ns, values) of the rows written, NaN where a signal
        has no value yet, for other recorders (run.mcap) to take the same rows.
        """
        if not self.tasks:
            return [], []
        horizon = max(self.delivered_ns.values()) if final else min(self.delivered_ns.values())
        streams = [[(t, task, row) for t, row in self.pending[task] if t <= horizon] for task in self.tasks]
        for task in self.tasks:
            self.pending[task] = [(t, row) for t, row in self.pending[task] if t > horizon]
        times: list[int] = []
        rows: list[list[float]] = []
        current_t: int | None = None
        for t_ns, task, row in heapq.merge(*streams, key=lambda item: item[0]):
            if current_t is not None and t_ns != current_t:
                times.append(current_t)
                rows.append(self._row())
            current_t = t_ns
            self.held[task] = row
        if current_t is not None:
            times.append(current_t)
            rows.append(self._row())
        self.file.writelines(_csv_line(t, row) for t, row in zip(times, rows, strict=True))
        self.rows_written += len(rows)
        self.file.flush()
        return times, rows

    def _row(self) -> list[float]:
        nan = float("nan")
        return [nan if (held := self.held[task]) is None else float(held[index]) for task, index in self.columns]

    def close(self) -> None:
        """Close the file; ``flush(final=True)`` first writes what is still pending."""
        self.file.close()


def _csv_line(t_ns: int, row: list[float]) -> str:
    cells = [repr(t_ns / 1e9)] + ["" if value != value else repr(value) for value in row]
    return ",".join(cells) + "\n"
