"""A connection's guard: ``min``, ``max`` and ``rate_per_s``, as a device's commands have.

A controller's output into a plant *model* (or into another task) is clamped to ``[min, max]``
and moved by at most ``rate_per_s · P`` per cycle of the reading task (P: its period), from the
value the input holds before T0 (its start value). It is applied where the reading task reads
its inputs (``ipc/wiring.py``, and the C hot path), the same in ``run``, ``simulate`` and
``replay``: a simulation sees the saturation a run sees. Each guarded input counts the cycles
it was clamped and the cycles its rate limit held it back (summary.json ``tasks.NAME.input_limits``).
"""

from __future__ import annotations

import math
from typing import Any

from rtloop.app.specs import Connection, SentName, SignalRef
from rtloop.errors import AppError
from rtloop.runnable import Runnable
from rtloop.text import shorten

App = Any
"""``rtloop.app.builder.App`` (builder imports this module: naming the class here would be a cycle)."""

LARGEST_LIMIT = 1e12
"""A bound beyond this is a typo (``1e308``), refused like a device's limits."""


def guarded_connection(what: str, source: SignalRef, target: SignalRef, allow_nonfinite: bool,
                       guard: tuple[object, object, object], device: Any = None) -> Connection:
    """The connection ``source → target`` with its guard ``(min, max, rate_per_s)`` checked;
    ``device``: the device at one of its ends, if any (its commands have limits of their own)."""
    if device is not None and any(value is not None for value in guard):
        raise AppError(f"{what}: a connection to or from a device has no min, max or rate_per_s of its own: "
                       f"the device's commands have theirs ([devices.{device.name}.limits]), and a reading "
                       "is guarded where the task uses it")
    low, high, rate = check_connection_guard(what, *guard, allow_nonfinite)
    return Connection(source, target, allow_nonfinite, low, high, rate)


def record_device_link(app: App, connection: Connection, device: str) -> None:
    """Record what crosses a device's connection: a reading as the task input it feeds (``rtloop
    replay`` plays it back without the device), a command as what the device was sent (after its
    limits: ``DEVICE.COMMAND`` beside the controller's value)."""
    target = connection.target
    if target.task in app.tasks:
        app.record(target)
    else:
        app.recorded.append(sent_signal(app, device, target.start, target.stop))


def check_connection_guard(what: str, low: object, high: object, rate_per_s: object,
                           allow_nonfinite: bool) -> tuple[float, float, float]:
    """``(min, max, rate_per_s)`` checked (None: no bound, no rate limit); one clear refusal else."""
    values = []
    for key, value, default in (("min", low, -math.inf), ("max", high, math.inf), ("rate_per_s", rate_per_s, math.inf)):
        if value is None:
            values.append(default)
            continue
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) \
                or abs(value) > LARGEST_LIMIT:
            raise AppError(f"{what}: {key} must be a finite number within ±{LARGEST_LIMIT:g}, got {shorten(value)}")
        values.append(float(value))
    low_f, high_f, rate_f = values
    if not low_f <= high_f:
        raise AppError(f"{what}: need min ≤ max, got min {low_f!r}, max {high_f!r}")
    if not rate_f > 0:
        raise AppError(f"{what}: rate_per_s must be > 0 (or absent: no limit), got {rate_f!r}")
    if allow_nonfinite and (low is not None or high is not None or rate_per_s is not None):
        raise AppError(f"{what}: allow_nonfinite and a limit (min, max, rate_per_s) do not go together: "
                       "a NaN cannot be clamped")
    return low_f, high_f, rate_f


# --- what a device was sent: recorded after its owner task's u ----------------------------------------

def sent_signal(app: App, device: str, start: int, stop: int) -> SignalRef:
    """Commands ``start:stop`` of ``device`` as they were sent (guarded), as the owner task records
    them: elements of its ``u`` past its own inputs (``TaskWiring.sent``, its devices in order)."""
    spec = app.devices[device]
    base = app.tasks[spec.task].runnable.n_inputs
    for other in app.devices.values():
        if other.name == device:
            break
        if other.task == spec.task:
            base += other.device.n_inputs
    return SignalRef(spec.task, "u", base + start, base + stop)


def sent_width(app: App, task: str) -> int:
    """How many commands ``task``'s devices are sent each cycle (recorded after its ``u``)."""
    return sum(spec.device.n_inputs for spec in app.devices.values() if spec.task == task)


def recorded_input_names(app: App, task: str) -> tuple[str, ...] | None:
    """Names for ``task``'s recorded inputs: its runnable's, then ``device.command`` (a ``SentName``)
    for each command its devices are sent; None when the runnable names none and it has no device."""
    runnable: Runnable = app.tasks[task].runnable
    own = runnable.input_names
    sent = [SentName(f"{spec.name}.{command}") for spec in app.devices.values() if spec.task == task
            for command in spec.device.command_names()]
    if not sent:
        return own
    padded = (*(own or ())[:runnable.n_inputs], *("",) * (runnable.n_inputs - len(own or ())))
    return (*padded, *sent)
