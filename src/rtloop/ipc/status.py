"""Small shared-memory blocks: the app's control block and one status block per task.

The control block carries the epoch T0, the end time and the stop flag from the
supervisor to every task. A task's status block carries live counters the other way,
for the supervisor, ``rtloop top`` and fault reports. Each word is written by one
side only, as a single aligned 8-byte store, so no locks are needed. The epoch is two
words that must be seen together: :func:`publish_epoch` and :func:`read_epoch` order them.
"""

from __future__ import annotations

from rtloop.ipc.schema import CONTROL_WORDS, STATUS_WORDS, ControlWord, StatusWord, TaskState
from rtloop.ipc.segments import Segment, fence

__all__ = ["CONTROL_WORDS", "STATUS_WORDS", "ControlWord", "StatusWord", "TaskState", "WordBlock", "publish_epoch",
           "read_epoch"]


class WordBlock:
    """A few int64 words at an offset of a segment, indexed by an IntEnum."""

    def __init__(self, segment: Segment, offset_bytes: int, count: int) -> None:
        self.words = segment.buffer[offset_bytes : offset_bytes + 8 * count].cast("q")

    def __getitem__(self, word: int) -> int:
        return self.words[word]

    def __setitem__(self, word: int, value: int) -> None:
        self.words[word] = value


def publish_epoch(control: WordBlock, t0_ns: int, end_ns: int) -> None:
    """Give the tasks their timeline: END first, then T0 (release), for tasks start when T0 is set."""
    control[ControlWord.END_NS] = end_ns
    fence()  # on aarch64 a task could otherwise see the new T0 beside END = 0
    control[ControlWord.T0_NS] = t0_ns


def read_epoch(control: WordBlock) -> tuple[int, int]:
    """(T0, END) as :func:`publish_epoch` left them; T0 = 0 while the epoch is not set."""
    t0_ns = control[ControlWord.T0_NS]
    fence()  # acquire: END is read after the T0 that announces it
    return t0_ns, control[ControlWord.END_NS]
