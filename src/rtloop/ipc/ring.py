"""One single-producer/single-consumer ring in shared memory: the Python twin of the C hot path's ``Queue``.

The producer (a real-time task) never blocks and never waits for the reader: when the ring is
full a record is dropped and counted. The consumer (the supervisor, a port client) drains every
waiting record in one batch. Layout, in 8-byte words (``schema.QueueWord``)::

    [written, read, dropped, width, capacity, -, -, -]    HEADER_WORDS
    capacity ticks (int64)                                 only a ring WITH_TICKS
    capacity records of width words (int64 or float64)

Two layouts are used: :class:`Int64Ring` (int64 records: a task's timing ring, its read log)
and :class:`SampleQueue` (a tick and a float64 row: the record queue, output ports, the input
log). The producer publishes ``written`` after the record (a fence orders them), the consumer
gives the slots back by publishing ``read`` after copying them out.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from rtloop.ipc.schema import HEADER_WORDS, QueueWord, ring_size_bytes
from rtloop.ipc.segments import Segment, fence

__all__ = ["HEADER_WORDS", "Int64Ring", "SampleQueue", "SpscRing"]


class SpscRing:
    """A bounded SPSC ring over a :class:`~rtloop.ipc.segments.Segment` at ``offset_bytes``."""

    HEADER_WORDS = HEADER_WORDS
    WITH_TICKS: ClassVar[bool] = False
    """Whether a tick (int64) goes beside each record, in a column of its own."""
    DTYPE: ClassVar[Any] = np.int64
    """The records' element type (8 bytes)."""

    def __init__(self, segment: Segment, offset_bytes: int = 0) -> None:
        data_at = offset_bytes + HEADER_WORDS * 8
        header = segment.buffer[offset_bytes:data_at].cast("q")
        self.width = int(header[QueueWord.WIDTH])
        self.capacity = int(header[QueueWord.CAPACITY])
        rows_at = data_at + (self.capacity * 8 if self.WITH_TICKS else 0)
        end = rows_at + self.capacity * self.width * 8
        self.memory = segment.buffer[offset_bytes:end]
        """Header, ticks and records as one buffer (what the compiled hot path holds)."""
        self.words = self.memory.cast("q")
        """The same as int64 words: single aligned 8-byte stores, and fast."""
        self.ticks = segment.array(np.int64, self.capacity, data_at) if self.WITH_TICKS else None
        self.rows = segment.array(self.DTYPE, self.capacity * self.width, rows_at).reshape(self.capacity, self.width)
        self._row_words = segment.buffer[rows_at:end].cast("q")
        self.written = int(header[QueueWord.WRITTEN])
        """What this producer has pushed (its own copy: the shared word is only ever stored)."""

    @classmethod
    def ring_bytes(cls, capacity: int, width: int) -> int:
        return ring_size_bytes(capacity, width + (1 if cls.WITH_TICKS else 0))

    @classmethod
    def create(cls, segment: Segment, capacity: int, width: int, offset_bytes: int = 0) -> Any:
        """Write an empty ring's header at ``offset_bytes`` and attach to it."""
        header = segment.buffer[offset_bytes:offset_bytes + HEADER_WORDS * 8].cast("q")
        for i in range(HEADER_WORDS):
            header[i] = 0
        header[QueueWord.WIDTH], header[QueueWord.CAPACITY] = width, capacity
        return cls(segment, offset_bytes)

    # --- producer side (real time): allocation-free ----------------------------------------------
    def _claim(self) -> int:
        """The slot of the next record, or -1 (a drop counted) when the ring is full."""
        words = self.words
        if self.written - words[QueueWord.READ] >= self.capacity:
            words[QueueWord.DROPPED] += 1
            return -1
        return self.written % self.capacity

    def _publish(self) -> None:
        fence()  # the record must be visible before the count that announces it
        self.written += 1
        self.words[QueueWord.WRITTEN] = self.written

    def push(self, tick: int, values: Any) -> bool:
        """Append ``values`` (a row of ``width``) with ``tick``; False (a drop counted) when full."""
        index = self._claim()
        if index < 0:
            return False
        if self.ticks is not None:
            self.ticks[index] = tick
        self.rows[index] = values
        self._publish()
        return True

    def push4(self, a: int, b: int, c: int, d: int) -> bool:
        """Append one 4-word int64 record by scalar stores (the timing ring's cheapest push)."""
        index = self._claim()
        if index < 0:
            return False
        base, data = index * 4, self._row_words
        data[base] = a
        data[base + 1] = b
        data[base + 2] = c
        data[base + 3] = d
        self._publish()
        return True

    # --- consumer side (not real time) -----------------------------------------------------------
    @property
    def sent(self) -> int:
        """Records pushed so far (not counting drops)."""
        return int(self.words[QueueWord.WRITTEN])

    @property
    def received(self) -> int:
        return int(self.words[QueueWord.READ])

    @property
    def dropped(self) -> int:
        return int(self.words[QueueWord.DROPPED])

    def _take(self, max_records: int | None) -> tuple[int, np.ndarray]:
        words = self.words
        written = words[QueueWord.WRITTEN]
        fence()  # acquire: the records are read after the count that announced them
        read = words[QueueWord.READ]
        count = written - read if max_records is None else min(written - read, max_records)
        return read, (read + np.arange(max(count, 0))) % self.capacity

    def _give_back(self, read: int, count: int) -> None:
        if count:
            fence()  # finish copying before handing the slots back to the producer
            self.words[QueueWord.READ] = read + count


class Int64Ring(SpscRing):
    """int64 records only: a task's timing ring, its read log. :meth:`drain` gives an n × width array."""

    @staticmethod
    def size_bytes(capacity: int, width: int) -> int:
        return Int64Ring.ring_bytes(capacity, width)

    @staticmethod
    def initialise(segment: Segment, capacity: int, width: int, offset_bytes: int = 0) -> Int64Ring:
        ring: Int64Ring = Int64Ring.create(segment, capacity, width, offset_bytes)
        return ring

    @property
    def written_total(self) -> int:
        return self.sent

    def drain(self, max_records: int | None = None) -> np.ndarray:
        """Copy out the records written since the last drain, at most ``max_records`` (shape: n × width)."""
        read, indices = self._take(max_records)
        records: np.ndarray = self.rows[indices].copy()
        self._give_back(read, len(indices))
        return records


class SampleQueue(SpscRing):
    """A tick and a float64 row per record: the record queue, output ports, the input log.
    :meth:`drain` gives (ticks, rows)."""

    WITH_TICKS = True
    DTYPE = np.float64

    @property
    def n_values(self) -> int:
        return self.width

    @staticmethod
    def size_bytes(n_values: int, capacity: int) -> int:
        return SampleQueue.ring_bytes(capacity, n_values)

    @classmethod
    def initialise(cls, segment: Segment, n_values: int, capacity: int, offset_bytes: int = 0) -> SampleQueue:
        queue: SampleQueue = cls.create(segment, capacity, n_values, offset_bytes)
        return queue

    def drain(self, max_rows: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Copy out the waiting records: (ticks, rows). Never blocks."""
        read, indices = self._take(max_rows)
        assert self.ticks is not None
        ticks, rows = self.ticks[indices].copy(), self.rows[indices].copy()
        self._give_back(read, len(indices))
        return ticks, rows
