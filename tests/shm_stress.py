"""Writer/reader processes for the torn-read stress test (importable by spawned processes)."""

from __future__ import annotations

import os

import numpy as np

from rtloop.ipc.channels import LetChannel
from rtloop.ipc.ring import SampleQueue
from rtloop.ipc.segments import Segment

N_VALUES = 16


def payloads(ticks: np.ndarray) -> np.ndarray:
    """The row of every k of ``ticks``: k*1000 + 0, 1, ... and a checksum last (a batch checked at once)."""
    values = np.arange(N_VALUES, dtype=np.float64)[None, :] + np.asarray(ticks, dtype=np.float64)[:, None] * 1000.0
    values[:, -1] = values[:, :-1].sum(axis=1)
    return values


def consistent_rows(rows: np.ndarray) -> np.ndarray:
    """Whether each row of ``rows`` is one whole payload: consecutive values and their checksum
    (reads copied into a block, checked in one go; two payloads mixed fail both)."""
    return (rows[:, -1] == rows[:, :-1].sum(axis=1)) & np.all(np.diff(rows[:, :-1], axis=1) == 1.0, axis=1)


# The writers take their rows from a table made before they start: the loop then spends its
# time in publish/push, so a reader meets a slot being written far more often per read (a reader
# without its seqlock's second sequence check sees about one torn copy in 1,500 reads this way,
# against one in 4,000 with each row made inside the loop) and the stress tests need fewer reads.
TABLE_ROWS = 1024  # a power of two: k & (TABLE_ROWS - 1) picks the row


def let_writer(segment_name: str, cpu: int, stop_name: str) -> None:
    os.sched_setaffinity(0, {cpu})
    channel = LetChannel(Segment.attach(segment_name))
    stop = Segment.attach(stop_name).buffer.cast("q")
    table = list(payloads(np.arange(TABLE_ROWS)))  # rows k*1000 + 0..14, so two rows never mix unseen
    k = 0
    while not stop[0]:
        k += 1
        channel.publish(k, table[k & (TABLE_ROWS - 1)])


def queue_writer(segment_name: str, cpu: int, count: int) -> None:
    os.sched_setaffinity(0, {cpu})
    queue = SampleQueue(Segment.attach(segment_name))
    table = list(payloads(np.arange(count)))  # row k is payload(k): the reader checks each row's tick
    k = 0
    while k < count:
        if queue.push(k, table[k]):
            k += 1
