"""Lock-free shared-memory channels: seqlock slots.

``LetChannel``    one writer task → any reader tasks. A ring of seqlock slots, each
                  stamped with the time its value becomes valid (logical execution time).
``LatestValue``   non-RT writers → one RT reader: a single seqlock slot (input ports).
(``SampleQueue``, one RT writer → one non-RT reader of every tick's values, is a ring:
:mod:`rtloop.ipc.ring`.)

Every class takes a :class:`~rtloop.ipc.segments.Segment` and an offset, so the same code runs
over ``/dev/shm`` between processes and over plain memory in the simulator. Word
stores are single aligned 8-byte writes; ordering comes from :func:`~rtloop.ipc.segments.fence`.
"""

from __future__ import annotations

import numpy as np

from rtloop.ipc.schema import HEADER_WORDS, NO_STAMP, READ_RETRIES, ChannelWord, PortWord, SlotWord
from rtloop.ipc.segments import Segment, fence

__all__ = ["HEADER_WORDS", "NO_STAMP", "READ_RETRIES", "LatestValue", "LetChannel"]


class LetChannel:
    """A ring of stamped seqlock slots holding one task's output vector.

    Header words: ``[published, n_values, n_slots]``. Slot i: ``[seq, stamp_ns, values…]``.
    A writer bumps ``seq`` to odd, writes, stamps, bumps it to even; a reader copies
    and accepts the copy only if ``seq`` was even and unchanged around it.
    """

    def __init__(self, segment: Segment, offset_bytes: int = 0) -> None:
        self.words = segment.buffer[offset_bytes:].cast("q")
        self.n_values = int(self.words[ChannelWord.N_VALUES])
        self.n_slots = int(self.words[ChannelWord.N_SLOTS])
        self.slot_words = SlotWord.VALUES + self.n_values
        floats = segment.array(
            np.float64, HEADER_WORDS + self.n_slots * self.slot_words, offset_bytes
        )
        self.bases = [self._base(i) for i in range(self.n_slots)]
        self.values = [floats[base + SlotWord.VALUES : base + SlotWord.VALUES + self.n_values] for base in self.bases]
        self.published = int(self.words[ChannelWord.PUBLISHED])

    @staticmethod
    def size_bytes(n_values: int, n_slots: int) -> int:
        return (HEADER_WORDS + n_slots * (SlotWord.VALUES + n_values)) * 8

    @classmethod
    def initialise(cls, segment: Segment, n_values: int, n_slots: int, offset_bytes: int = 0) -> LetChannel:
        words = segment.buffer[offset_bytes:].cast("q")
        for i in range(HEADER_WORDS + n_slots * (SlotWord.VALUES + n_values)):
            words[i] = 0
        words[ChannelWord.N_VALUES], words[ChannelWord.N_SLOTS] = n_values, n_slots
        for i in range(n_slots):
            words[HEADER_WORDS + i * (SlotWord.VALUES + n_values) + SlotWord.STAMP_NS] = NO_STAMP
        return cls(segment, offset_bytes)

    def _base(self, slot: int) -> int:
        return HEADER_WORDS + slot * self.slot_words

    # --- writer (RT) ---------------------------------------------------------------------
    def publish(self, stamp_ns: int, values: np.ndarray) -> None:
        words = self.words
        published = self.published
        slot = published % self.n_slots
        base = self.bases[slot]
        seq = words[base + SlotWord.SEQ] + 1
        words[base + SlotWord.SEQ] = seq  # odd: slot being written
        fence()
        self.values[slot][:] = values
        words[base + SlotWord.STAMP_NS] = stamp_ns
        fence()
        words[base + SlotWord.SEQ] = seq + 1  # even: slot complete
        self.published = published + 1
        words[ChannelWord.PUBLISHED] = published + 1

    # --- reader (RT) ---------------------------------------------------------------------
    def source_views(self, source: slice) -> list[np.ndarray]:
        """``values[source]`` of every slot, made once so that reads do not slice."""
        return [values[source] for values in self.values]

    def read_valid_at(self, time_ns: int, sources: list[np.ndarray], out: np.ndarray) -> int:
        """Copy the newest slot stamped ≤ ``time_ns`` (its ``sources`` view) into ``out``.

        Returns that slot's stamp, or NO_STAMP if no such slot exists (``out`` untouched).
        ``published`` only says where to start looking; each slot's seqlock decides.
        """
        words, bases, n_slots = self.words, self.bases, self.n_slots
        published = words[ChannelWord.PUBLISHED]
        back, tries = 1, 0
        while back <= published and back <= n_slots and tries < READ_RETRIES * n_slots:
            tries += 1
            slot = (published - back) % n_slots
            base = bases[slot]
            seq = words[base + SlotWord.SEQ]
            if seq & 1:
                continue  # being written: look again
            fence()
            stamp = words[base + SlotWord.STAMP_NS]
            if stamp <= time_ns:
                np.copyto(out, sources[slot])
            fence()
            if words[base + SlotWord.SEQ] != seq:
                continue  # changed under us: look again (the writer may have lapped it)
            if stamp <= time_ns:
                return stamp
            back += 1  # too new for this reader: try the slot before
        return NO_STAMP


class LatestValue:
    """One seqlock slot: non-RT writers post values, one RT reader takes the newest.

    Header words: ``[seq, writes, reads, n_values, fed_by_profile]`` then the values.
    Writers from several processes must serialise among themselves (the port client
    holds an ``flock`` while writing); the RT reader never waits for them.
    """

    def __init__(self, segment: Segment, offset_bytes: int = 0) -> None:
        self.words = segment.buffer[offset_bytes:].cast("q")
        self.n_values = int(self.words[PortWord.N_VALUES])
        self.values = segment.array(np.float64, HEADER_WORDS + self.n_values, offset_bytes)[
            HEADER_WORDS:
        ]
        self.scratch = np.zeros(self.n_values)  # a torn copy never reaches the reader's array
        self.last_seq_seen = 0

    @staticmethod
    def size_bytes(n_values: int) -> int:
        return (HEADER_WORDS + n_values) * 8

    @classmethod
    def initialise(
        cls, segment: Segment, initial: np.ndarray, offset_bytes: int = 0, *, fed_by_profile: bool = False
    ) -> LatestValue:
        words = segment.buffer[offset_bytes:].cast("q")
        for i in range(HEADER_WORDS):
            words[i] = 0
        words[PortWord.N_VALUES] = len(initial)
        words[PortWord.FED_BY_PROFILE] = int(fed_by_profile)
        channel = cls(segment, offset_bytes)
        channel.values[:] = initial
        return channel

    @property
    def fed_by_profile(self) -> bool:
        return bool(self.words[PortWord.FED_BY_PROFILE])

    @property
    def writes(self) -> int:
        return int(self.words[PortWord.WRITES])

    @property
    def reads(self) -> int:
        return int(self.words[PortWord.READS])

    def write(self, values: np.ndarray) -> None:
        words = self.words
        words[PortWord.SEQ] += 1
        fence()
        self.values[:] = values
        fence()
        words[PortWord.SEQ] += 1
        words[PortWord.WRITES] += 1

    def peek(self) -> np.ndarray | None:
        """The newest complete value, for a non-RT onlooker (not counted as the task's read)."""
        words = self.words
        for _ in range(READ_RETRIES):
            seq = words[PortWord.SEQ]
            if seq & 1:
                continue
            fence()
            values = np.array(self.values)
            fence()
            if words[PortWord.SEQ] == seq:
                return values
        return None

    def read_into(self, out: np.ndarray) -> bool:
        """Copy the newest complete value into ``out``; False if none could be read."""
        words = self.words
        for _ in range(READ_RETRIES):
            seq = words[PortWord.SEQ]
            if seq & 1:
                continue
            fence()
            np.copyto(self.scratch, self.values)
            fence()
            if words[PortWord.SEQ] == seq:
                np.copyto(out, self.scratch)
                if seq != self.last_seq_seen:
                    self.last_seq_seen = seq
                    words[PortWord.READS] += 1
                return True
        return False
