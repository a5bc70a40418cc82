"""Every word and offset of rtloop's shared memory, declared once.

Shared memory is an array of 8-byte words (int64, or float64 for values). This module
names each word of each block; the Python classes (``status``, ``channels``,
``segments``) index with these names, and the C hot path includes ``_schema.h``,
generated from here (``python -m rtloop.ipc.schema > src/rtloop/ipc/_schema.h``). A test
checks that the header is up to date and that the built extension agrees with every
constant (:func:`constants`); ``hotpath`` refuses a built extension that does not.

Blocks (word indices):

- control block (one per app): :class:`ControlWord`, ``CONTROL_WORDS`` long.
- task segment (one per task): a status block (:class:`StatusWord`, ``STATUS_WORDS``)
  then the timing ring at :data:`TASK_TIMING_OFFSET_BYTES`.
- rings and queues (timing ring, sample queues, record and input-log queues): a
  ``HEADER_WORDS`` header (:class:`QueueWord`) then, for a sample queue, ``capacity``
  ticks and ``capacity × width`` values; for a record ring ``capacity × width`` records.
  A timing record is :class:`TimingField` (``TIMING_RECORD_WORDS`` words), a read-log
  record :class:`ReadLogField`.
- LET channel (a task's outputs): header :class:`ChannelWord`, then ``n_slots`` slots of
  ``[SlotWord.SEQ, SlotWord.STAMP_NS, values…]``.
- live port (LatestValue): header :class:`PortWord`, values from ``HEADER_WORDS``.

And the mode both twins of the hot path are told about: :class:`NudgeMode`.
"""

from __future__ import annotations

import enum
import sys

import numpy as np


class ControlWord(enum.IntEnum):
    """The app's control block: supervisor → every task."""

    T0_NS = 0
    END_NS = 1
    STOP = 2
    SNAPSHOT_NS = 3
    """A --keep run asks every task for its state before its first release at or after this time."""


class StatusWord(enum.IntEnum):
    """A task's status block: task → supervisor, ``rtloop top``, fault reports.

    Words 7, 9, 10, 11, 13 and 14 are retired (a maximum latency and execution time, the policy,
    priority and real-time flag, the timing records dropped: written, never read; the pipe's
    ``settings`` message and the timing ring's own header say them). The others keep their
    places, so a hot path built before stays valid."""

    STATE = 0
    """A :class:`TaskState`."""
    PID = 1
    CYCLE = 2
    OVERRUNS = 3
    DEADLINE_MISSES = 4
    STALE_READS = 5
    LATENCY_LAST_NS = 6
    EXEC_LAST_NS = 8
    CPU = 12
    MISSES_IN_A_ROW_MAX = 15
    NONFINITE_VALUES = 16
    """NaN or ±inf outputs headed across a connection (each output of each cycle counts once)."""
    NONFINITE_FIRST_CYCLE = 17
    NONFINITE_FIRST_OUTPUT = 18
    """The first one: its cycle and its index in ``y``."""


class TaskState(enum.IntEnum):
    """The ``STATE`` word of a task's status block, in the order a task goes through them."""

    STARTING = 0
    READY = 1
    RUNNING = 2
    STOPPED = 3
    FAILED = 4
    POSTRUN = 5


class QueueWord(enum.IntEnum):
    """Header of a single-producer ring or queue (Int64Ring, SampleQueue)."""

    WRITTEN = 0
    READ = 1
    DROPPED = 2
    WIDTH = 3
    CAPACITY = 4


class ChannelWord(enum.IntEnum):
    """Header of a LET channel (LetChannel)."""

    PUBLISHED = 0
    N_VALUES = 1
    N_SLOTS = 2


class SlotWord(enum.IntEnum):
    """One slot of a LET channel; the values follow from ``VALUES``."""

    SEQ = 0
    STAMP_NS = 1
    VALUES = 2


class PortWord(enum.IntEnum):
    """Header of a live input port (LatestValue); the values follow from ``HEADER_WORDS``."""

    SEQ = 0
    WRITES = 1
    READS = 2
    N_VALUES = 3
    FED_BY_PROFILE = 4


class TimingField(enum.IntEnum):
    """One record of a task's timing ring."""

    CYCLE = 0
    RELEASE_NS = 1
    START_NS = 2
    END_NS = 3


class ReadLogField(enum.IntEnum):
    """One record of a task's read log: a read that got another sample than LET promised (for replay)."""

    RELEASE_NS = 0
    """The release that read, in ns since T0."""
    WRITER = 1
    """Which of the task's writers (its place among them)."""
    STAMP_GOT_NS = 2
    """The stamp of the sample it got, ns since T0 (NO_STAMP: none)."""
    STAMP_DUE_NS = 3
    """The stamp it was entitled to, ns since T0."""


class NudgeMode(enum.IntEnum):
    """How live writes to a port fed by a profile combine with it (``add_profile``)."""

    NONE = 0
    OFFSET = 1
    """u = the row in force + the latest live value."""
    OVERRIDE = 2
    """The newest of a row and a live write holds."""


HEADER_WORDS = 8
"""Every ring, queue, channel and port starts with this many header words."""
CONTROL_WORDS = 8
STATUS_WORDS = 32
TIMING_RECORD_WORDS = len(TimingField)
READ_LOG_RECORD_WORDS = len(ReadLogField)
TASK_TIMING_OFFSET_BYTES = STATUS_WORDS * 8
"""Where a task segment's timing ring starts (its status block comes first)."""
NO_STAMP = -(2**62)
"""The stamp of a LET slot never written."""
INITIAL_STAMP = 0
"""The stamp of a task's initial outputs, published at prerun (before T0 is known): a reader takes
it as stamped T0. So they are there before any task's first release, however late a task starts."""
READ_RETRIES = 64
"""Seqlock read attempts (per slot) before a reader gives up for this cycle."""
STOP_POLL_NS = 100_000_000
"""A task sleeping towards a release further away than this looks at the stop flag this often."""

TIMING_RECORD = np.dtype([(field.name.lower(), np.int64) for field in TimingField])
"""A timing record as a numpy structured type (``records.view(TIMING_RECORD)``)."""


def ring_size_bytes(capacity: int, width: int) -> int:
    """Bytes of a record ring of ``capacity`` records of ``width`` words."""
    return (HEADER_WORDS + capacity * width) * 8


def task_segment_size(timing_capacity: int) -> int:
    """Bytes of a task segment: status block, then a timing ring of ``timing_capacity`` records."""
    return TASK_TIMING_OFFSET_BYTES + ring_size_bytes(timing_capacity, TIMING_RECORD_WORDS)


_BLOCKS: tuple[tuple[str, type[enum.IntEnum]], ...] = (
    ("CONTROL", ControlWord), ("STATUS", StatusWord), ("QUEUE", QueueWord), ("CHANNEL", ChannelWord),
    ("SLOT", SlotWord), ("PORT", PortWord), ("TIMING", TimingField), ("READ_LOG", ReadLogField),
    ("NUDGE", NudgeMode),
)


def constants() -> dict[str, int]:
    """Every constant of the schema by its C name (what ``_hotpath.SCHEMA`` must equal)."""
    named = {f"{prefix}_{word.name}": int(word) for prefix, block in _BLOCKS for word in block}
    named.update(HEADER_WORDS=HEADER_WORDS, CONTROL_WORDS=CONTROL_WORDS, STATUS_WORDS=STATUS_WORDS,
                 TIMING_RECORD_WORDS=TIMING_RECORD_WORDS, READ_LOG_RECORD_WORDS=READ_LOG_RECORD_WORDS,
                 NO_STAMP=NO_STAMP, INITIAL_STAMP=INITIAL_STAMP, READ_RETRIES=READ_RETRIES,
                 STOP_POLL_NS=STOP_POLL_NS)
    return named


def c_header() -> str:
    """``_schema.h``: the constants as C macros, and an X-macro list the extension exports."""
    lines = ["/* Generated from rtloop/ipc/schema.py by `python -m rtloop.ipc.schema`: do not edit. */",
             "#ifndef RTLOOP_SCHEMA_H", "#define RTLOOP_SCHEMA_H", ""]
    named = constants()
    lines += [f"#define {name} (INT64_C({value}))" for name, value in named.items()]
    lines += ["", "/* X(NAME) for every constant: the extension exports them as _hotpath.SCHEMA */",
              "#define RTLOOP_SCHEMA(X) \\"]
    lines += [f"    X({name}) \\" for name in named]
    lines += ["", "#endif", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.stdout.write(c_header())
