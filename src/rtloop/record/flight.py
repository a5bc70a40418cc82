"""The flight recorder: a recording that keeps the last ``keep_s`` seconds and what surrounds events.

A run that lasts for days cannot keep every cycle on disk. With ``--keep S`` the recorder
writes its files (timing.csv, signals.csv, run.mcap, inputs.csv, reads.csv, the task
snapshots) in *segments* of S/6 seconds of run time, in ``DIR/segments/``. When a segment
is complete the window drops every older segment that holds nothing of the last S seconds,
unless it is *pinned*: a deadline miss, a stale read or a fault pins the segment it happened
in, the one before and the one after, so the cycles just before and just after every event
are kept. At most ``MAX_PINNED_SEGMENTS`` are pinned; later events are counted, not kept
(the last S seconds are always kept). At the end, :meth:`FlightWindow.stitch` joins the
segments left into the usual files and removes the folder.

The window keeps one segment more than the last S seconds need: the tasks' state is
saved a little after a segment starts (``runtime/snapshot.py``), so the segment before the
last S seconds holds the snapshot a replay of those S seconds starts from.

Disk bound: at most ``WINDOW_SEGMENTS + 2`` segments of the window plus
``MAX_PINNED_SEGMENTS`` pinned ones, i.e. (8 + 12)·S/6 ≈ 3.3·S seconds' worth of recording,
plus one extra copy of run.mcap while it is stitched.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from rtloop.record.mcap_writer import merge_mcap_files

SEGMENTS_DIR = "segments"
WINDOW_SEGMENTS = 6
MAX_PINNED_SEGMENTS = 12
MIN_SEGMENT_NS = 1_000_000_000


@dataclass
class RecordingSegment:
    """A stretch of the recording in its own files (the flight window keeps the newest few);
    not a shared-memory :class:`~rtloop.ipc.segments.Segment`."""

    index: int
    start_ns: int
    """Run time (since T0) of the first data it holds."""
    end_ns: int | None = None
    """Run time at which the next segment took over (None: still being written)."""
    pinned: bool = False


class FlightWindow:
    def __init__(self, out: Path, keep_s: float) -> None:
        self.directory = out / SEGMENTS_DIR
        self.keep_ns = round(keep_s * 1e9)
        self.segment_ns = max(MIN_SEGMENT_NS, self.keep_ns // WINDOW_SEGMENTS)
        self.segments = [RecordingSegment(0, 0)]
        self.pin_next = False
        self.events = 0
        """Events (misses, stale reads, faults) reported."""
        self.events_not_kept = 0
        """Events whose segments could not be pinned (the pin budget was spent)."""
        self.directory.mkdir(parents=True, exist_ok=True)
        for stale in self.directory.iterdir():  # left by an earlier run into the same folder
            stale.unlink()

    @property
    def current(self) -> RecordingSegment:
        return self.segments[-1]

    def path(self, name: str, segment: RecordingSegment | None = None) -> Path:
        """Where ``name`` (``timing.csv``, ...) of ``segment`` (default: the current one) goes."""
        return self.directory / f"{(segment or self.current).index:06d}-{name}"

    def due(self, latest_ns: int) -> bool:
        """Whether the current segment is full, the newest data being at run time ``latest_ns``."""
        return latest_ns >= self.current.start_ns + self.segment_ns

    def rotate(self, latest_ns: int, names: list[str]) -> None:
        """Start a new segment at ``latest_ns``; delete the files of segments no longer needed."""
        self.current.end_ns = latest_ns
        self.segments.append(RecordingSegment(self.current.index + 1, latest_ns, pinned=self.pin_next))
        self.pin_next = False
        horizon_ns = latest_ns - self.keep_ns - self.segment_ns  # one more: its snapshot starts the replay
        kept: list[RecordingSegment] = []
        for segment in self.segments:
            if segment.end_ns is not None and segment.end_ns <= horizon_ns and not segment.pinned:
                for name in names:
                    self.path(name, segment).unlink(missing_ok=True)
            else:
                kept.append(segment)
        self.segments = kept

    def mark_event(self) -> None:
        """Keep the segment being written, the one before and the one after."""
        self.events += 1
        wanted = [s for s in self.segments[-2:] if not s.pinned]
        if self.current.pinned and self.pin_next and not wanted:
            return  # already covered
        pinned = sum(s.pinned for s in self.segments) + self.pin_next
        if pinned + len(wanted) + (not self.pin_next) > MAX_PINNED_SEGMENTS:
            self.events_not_kept += 1
            return
        for segment in wanted:
            segment.pinned = True
        self.pin_next = True

    def stitch(self, out: Path, names: list[str]) -> None:
        """Join the kept segments into ``out/NAME`` for each name; remove the segments folder."""
        for name in names:
            parts = [self.path(name, s) for s in self.segments if self.path(name, s).exists()]
            if not parts:
                continue
            target = out / name
            if name.endswith(".pkl"):  # one file per segment, kept side by side: NNNNNN.pkl
                folder = out / name.removesuffix(".pkl")
                folder.mkdir(exist_ok=True)
                for old in folder.glob("*.pkl"):  # an earlier run's, in the same folder
                    old.unlink()
                for part in parts:
                    os.replace(part, folder / f"{part.name.removesuffix(f'-{name}')}.pkl")
                continue
            if name.endswith(".mcap"):
                if len(parts) == 1:
                    os.replace(parts[0], target)
                else:
                    merge_mcap_files(parts, target)
                    for part in parts:
                        part.unlink()
                continue
            os.replace(parts[0], target)
            with open(target, "ab") as joined:
                for part in parts[1:]:
                    with open(part, "rb") as source:
                        source.readline()  # the header, already there
                        shutil.copyfileobj(source, joined)
                    part.unlink()  # now: a full disk needs room for one segment only
        shutil.rmtree(self.directory, ignore_errors=True)

    def to_json(self) -> dict[str, object]:
        return {"segment_s": self.segment_ns / 1e9, "events": self.events,
                "events_not_kept": self.events_not_kept,
                "pinned_segments": sum(s.pinned for s in self.segments)}
