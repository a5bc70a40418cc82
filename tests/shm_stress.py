"""Writer/reader processes for the torn-read stress test (importable by spawned processes)."""

from __future__ import annotations

import os

import numpy as np

from rtloop.ipc.channels import LetChannel
from rtloop.ipc.ring import SampleQueue
from rtloop.ipc.segments import Segment

N_VALUES = 16


def payload(k: int) -> np.ndarray:
    values = np.arange(N_VALUES, dtype=np.float64) + k * 1000.0
    values[-1] = values[:-1].sum()  # checksum
    return values


def payloads(ticks: np.ndarray) -> np.ndarray:
    """``payload(k)`` for every k of ``ticks``, one row each (a whole drained batch checked at once)."""
    values = np.arange(N_VALUES, dtype=np.float64)[None, :] + np.asarray(ticks, dtype=np.float64)[:, None] * 1000.0
    values[:, -1] = values[:, :-1].sum(axis=1)
    return values


def is_consistent(values: np.ndarray) -> bool:
    return values[-1] == values[:-1].sum() and np.all(np.diff(values[:-1]) == 1.0)


def consistent_rows(rows: np.ndarray) -> np.ndarray:
    """``is_consistent`` of every row of ``rows`` (reads copied into a block, checked in one go)."""
    return (rows[:, -1] == rows[:, :-1].sum(axis=1)) & np.all(np.diff(rows[:, :-1], axis=1) == 1.0, axis=1)


def let_writer(segment_name: str, cpu: int, stop_name: str) -> None:
    os.sched_setaffinity(0, {cpu})
    channel = LetChannel(Segment.attach(segment_name))
    stop = Segment.attach(stop_name).buffer.cast("q")
    k = 0
    while not stop[0]:
        k += 1
        channel.publish(k, payload(k))


def queue_writer(segment_name: str, cpu: int, count: int) -> None:
    os.sched_setaffinity(0, {cpu})
    queue = SampleQueue(Segment.attach(segment_name))
    k = 0
    while k < count:
        if queue.push(k, payload(k)):
            k += 1
