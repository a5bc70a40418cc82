"""Checking a stream of messages (a ROS 2 topic, the Foxglove live view's input) before it reaches a task.

A bridge must never pass a message of the wrong size or a NaN into a controller, and
must not flood the log when a misconfigured node sends a bad message at 1 kHz. So:
:func:`~rtloop.ipc.values.validate_values` (the one check every port's values pass) checks
one message, :class:`RateLimitedWarner` limits how often a problem is logged, and
:class:`MessageValidator` combines both and counts what was accepted and rejected.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rtloop.ipc.values import REASONS, RejectedValues, validate_values

logger = logging.getLogger("rtloop.ros")

class RateLimitedWarner:
    """Logs a warning at most once per ``interval_s`` for each key.

    Warnings held back are counted and reported with the next one that is logged,
    e.g. ``"... (12 similar warnings suppressed)"``.

    Args:
        interval_s: minimum time between two warnings with the same key.
        emit: where warnings go; the ``rtloop.ros`` logger by default.
        clock: monotonic time in seconds; injectable for tests.
    """

    def __init__(
        self,
        interval_s: float = 1.0,
        emit: Callable[[str], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.interval_s = interval_s
        self._emit = emit or logger.warning
        self._clock = clock
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warn(self, message: str, key: str = "") -> bool:
        """Log ``message`` unless a warning with ``key`` was logged too recently.

        Returns:
            Whether the message was logged.
        """
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self.interval_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return False
        suppressed = self._suppressed.pop(key, 0)
        if suppressed:
            message += f" ({suppressed} similar warning(s) suppressed)"
        self._last[key] = now
        self._emit(message)
        return True

    def suppressed(self, key: str = "") -> int:
        """Return how many warnings with ``key`` are held back since the last one logged."""
        return self._suppressed.get(key, 0)


@dataclass
class RejectCounts:
    """How many incoming messages a :class:`MessageValidator` accepted and rejected."""

    accepted: int = 0
    """Messages passed on."""
    rejected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REASONS, 0))
    """Messages dropped, by reason (see :data:`REASONS`)."""

    @property
    def total_rejected(self) -> int:
        """All dropped messages, whatever the reason."""
        return sum(self.rejected.values())

    def to_json(self) -> dict[str, Any]:
        """Return the counts as plain JSON data (for ``summary.json``)."""
        return {"accepted": self.accepted, "rejected": self.total_rejected,
                "rejected_by_reason": dict(self.rejected)}


class MessageValidator:
    """Validates, counts and rate-limits warnings for the messages of one topic.

    Args:
        expected_length: elements of the port the messages feed.
        allow_nonfinite: accept NaN and ±inf.
        what: name used in warnings, e.g. the topic.
        warner: shared :class:`RateLimitedWarner`; a new one (1 s interval) if omitted.
        value_range: ``(lo, hi)`` the values must lie in (counted under ``range`` otherwise).
    """

    def __init__(
        self,
        expected_length: int,
        allow_nonfinite: bool = False,
        what: str = "message",
        warner: RateLimitedWarner | None = None,
        value_range: tuple[float, float] | None = None,
    ) -> None:
        self.expected_length = expected_length
        self.value_range = value_range
        self.allow_nonfinite = allow_nonfinite
        self.what = what
        self.warner = warner or RateLimitedWarner()
        self.counts = RejectCounts()

    def check(self, values: Any) -> np.ndarray | None:
        """Return the values as a float64 array, or ``None`` if rejected (counted, warned)."""
        try:
            array = validate_values(values, self.expected_length, allow_nonfinite=self.allow_nonfinite,
                                    where=self.what, value_range=self.value_range)
        except RejectedValues as exc:
            self.counts.rejected[exc.reason] += 1
            self.warner.warn(f"dropped {exc}", key=f"{self.what}:{exc.reason}")
            return None
        self.counts.accepted += 1
        return array
