"""The guard between a task's outputs and a device: finite, clamped, rate limited.

Every command passes here before a driver sees it, in this order:

1. a non-finite value (NaN, ±inf) is a fault (:class:`DeviceFault` naming the task, the
   cycle and the command): it never reaches a wire, and the run ends with safe values;
2. clamped to ``[min, max]``;
3. moved towards it by at most ``rate_per_s · P`` per cycle (from the safe value at T0,
   the state a device is left in before activation).

Each command counts the cycles its value was clamped (``clamped``) and the cycles its rate limit
held it back (``rate_limited``): summary.json says them, and ``out`` (what the device got) is
recorded beside the controller's value, so a limit that acts is never invisible.

All of it works in arrays allocated once: nothing is allocated per cycle.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rtloop.io.device import CommandLimit, FloatVector, fault


class CommandGuard:
    """Limits for the ``n`` commands of one device, at one task period."""

    def __init__(self, limits: Sequence[CommandLimit], period_ns: int, labels: Sequence[str],
                 let: bool = False, out: FloatVector | None = None) -> None:
        self.low = np.array([limit.min for limit in limits], dtype=np.float64)
        self.high = np.array([limit.max for limit in limits], dtype=np.float64)
        self.safe = np.array([limit.safe for limit in limits], dtype=np.float64)
        self.step_max = np.array([limit.rate_per_s * period_ns * 1e-9 for limit in limits], dtype=np.float64)
        self.step_min = -self.step_max
        self.last = self.safe.copy()  # what was written last: the safe state before T0
        self.out = np.zeros(len(limits)) if out is None else out
        """What the device was sent last (a view of the task's recorded ``sent`` values, when given)."""
        self.out[:] = self.safe  # written at configure: what the device holds until the first write
        self._delta = np.zeros(len(limits))
        self._hit = np.zeros(len(limits), dtype=bool)
        self.clamped = np.zeros(len(limits), dtype=np.int64)
        """Per command: cycles whose value was outside ``[min, max]`` (sent clamped)."""
        self.rate_limited_cycles = np.zeros(len(limits), dtype=np.int64)
        """Per command: cycles whose step was more than ``rate_per_s · P`` (sent held back)."""
        self.rate_limited = bool(np.isfinite(self.step_max).any())
        self._finite = np.zeros(len(limits), dtype=bool)
        self.labels = tuple(labels)
        self.let = let
        """Commands written at the release after the step that computed them (``io = "let"``): a fault says so."""

    def apply(self, u: FloatVector, task: str, cycle: int) -> FloatVector:
        """The command to write for ``u``: checked, clamped, rate limited (in ``self.out``).

        Plain ufuncs with ``out=`` only (``np.clip`` and ``ndarray.all`` go through Python
        wrappers that cost several times more; arithmetic on a NaN or inf would warn); the
        rate limit's four only where one is set."""
        delta = self._delta
        out = self.out
        last = self.last
        finite = self._finite  # (one name a line: a tuple here would be the only object a cycle makes)
        np.isfinite(u, out=finite)
        if np.count_nonzero(finite) != len(finite):
            index = int(np.argmin(finite))
            when = f" (computed by the step of cycle {cycle - 1}, due at this release: io = let)" if self.let else ""
            raise fault(task, cycle, self.labels[index], f"command {float(u[index])!r} is not finite{when}; "
                        "it was not sent (the device gets its safe value)")
        hit = self._hit
        np.minimum(u, self.high, out=out)
        np.maximum(out, self.low, out=out)
        np.not_equal(out, u, out=hit)
        np.add(self.clamped, hit, out=self.clamped)
        if self.rate_limited:
            np.subtract(out, last, out=delta)
            np.greater(delta, self.step_max, out=hit)  # (two comparisons: np.abs would be one more ufunc)
            np.add(self.rate_limited_cycles, hit, out=self.rate_limited_cycles)
            np.less(delta, self.step_min, out=hit)
            np.add(self.rate_limited_cycles, hit, out=self.rate_limited_cycles)
            np.minimum(delta, self.step_max, out=delta)
            np.maximum(delta, self.step_min, out=delta)
            np.add(last, delta, out=out)
        np.copyto(last, out)
        return out

    def counts(self, names: Sequence[str]) -> dict[str, dict[str, int]]:
        """``clamped_cycles`` and ``rate_limited_cycles`` per command name (only those that acted)."""
        return {"clamped_cycles": {name: int(n) for name, n in zip(names, self.clamped.tolist(), strict=True) if n},
                "rate_limited_cycles": {name: int(n) for name, n in
                                        zip(names, self.rate_limited_cycles.tolist(), strict=True) if n}}

    def safe_values(self) -> FloatVector:
        """The safe values (remembered as the last command written)."""
        self.last[:] = self.safe
        return self.safe
