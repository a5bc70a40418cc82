"""A task's devices, run inside the task's process: when they are read and written, and how they stop.

Per cycle (the task's loop calls these; ``docs/devices.md`` has the timeline):

- :meth:`TaskDevices.at_release`, right after the sleep to release t, before ``step``:
  ``let`` devices write the commands of the job released at t − P (held in the task's
  ``y`` since then: logical execution time), then every device is read and its readings
  are copied into the task's inputs;
- :meth:`TaskDevices.after_step`: ``immediate`` devices write the job's commands now.

Every command goes through the device's :class:`~rtloop.io.limits.CommandGuard` first.
:meth:`TaskDevices.stop` writes each device's safe values, then deactivates and closes it;
the task calls it on every way out of its loop, before anything else.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rtloop.errors import AFTER_STEP_PHASE, RELEASE_PHASE, DeviceError, DeviceFault
from rtloop.io.compiled import devio, refused
from rtloop.io.device import CommandLimit, Device, FloatVector, fault
from rtloop.io.kernel import GPIO_V2_LINE_VALUES
from rtloop.io.limits import CommandGuard
from rtloop.linux import rt


@dataclass(frozen=True, slots=True)
class DeviceWiring:
    """One device of a task, as the task process needs it (picklable)."""

    device: Device
    io: str
    """``let`` or ``immediate``."""
    limits: tuple[CommandLimit, ...]
    commands: tuple[tuple[slice, slice], ...]
    """(task ``y`` slice → device ``u`` slice) for each connection into the device."""
    readings: tuple[tuple[slice, slice], ...]
    """(device ``y`` slice → task ``u`` slice) for each connection out of it."""
    source: str = "<python>"
    """The app file (for errors)."""
    readings_allow_nonfinite: tuple[bool, ...] = ()
    """Per reading connection: ``allow_nonfinite`` (default: none does, a NaN reading is a fault)."""


STALE_CYCLES_KEPT = 100
"""The first cycles that read stale values, kept per device for summary.json (and so for replay)."""


class _Slot:
    """One device with its vectors, its guard and its copies from and to the task's vectors."""

    __slots__ = ("checked_readings", "command_copies", "compiled_guard", "compiled_readings", "compiled_unchecked",
                 "device", "guard", "reading_copies", "reading_labels", "stale_cycles", "stale_first", "stale_last",
                 "stale_longest", "stale_run", "stale_seen", "u", "y")

    def __init__(self, wiring: DeviceWiring, period_ns: int, task_u: FloatVector, task_y: FloatVector,
                 sent: FloatVector | None = None) -> None:
        device = self.device = wiring.device
        name = device.name
        labels = [f"{name}.u[{i}] ({command})" for i, command in enumerate(device.command_names())]
        self.guard = CommandGuard(wiring.limits, period_ns, labels, let=wiring.io == "let", out=sent)
        self.u = self.guard.safe.copy()  # a command nothing is wired to stays at its safe value
        self.y = np.zeros(device.n_outputs)
        self.command_copies = [(task_y[source], self.u[target]) for source, target in wiring.commands]
        self.reading_copies = [(self.y[source], task_u[target]) for source, target in wiring.readings]
        # A reading crosses into the task finite, as a task's output does, unless its connection
        # allows NaN and ±inf: a NaN speed through a controller's min/max clamp is full voltage.
        allowed = wiring.readings_allow_nonfinite or (False,) * len(wiring.readings)
        checked = [copy for copy, allow in zip(self.reading_copies, allowed, strict=True) if not allow]
        unchecked = [copy for copy, allow in zip(self.reading_copies, allowed, strict=True) if allow]
        self.checked_readings = [(source.start or 0, self.y[source], np.zeros(self.y[source].size, dtype=bool))
                                 for (source, _), allow in zip(wiring.readings, allowed, strict=True) if not allow]
        self.reading_labels = [f"{name}.y[{i}] ({reading})" for i, reading in enumerate(device.reading_names())]
        # The copies and the guard in one C call each (io/_devio.c), where it was built and the
        # vectors are contiguous; the numpy code stays the reference (same numbers, bit for bit).
        self.compiled_guard = self.compiled_readings = self.compiled_unchecked = None
        compiled = devio()
        if compiled is not None:
            guard = self.guard
            try:
                self.compiled_guard = compiled.Guard(self.u, guard.low, guard.high, guard.step_max, guard.last,
                                                     guard.out, guard.clamped, guard.rate_limited_cycles,
                                                     self.command_copies, guard.rate_limited)
                self.compiled_readings = compiled.Copies(checked)  # returns where a value is not finite
                self.compiled_unchecked = compiled.Copies(unchecked) if unchecked else None
            except (ValueError, BufferError):  # a strided slice: the numpy way
                self.compiled_guard = self.compiled_readings = self.compiled_unchecked = None
            except TypeError as error:  # the build and this side disagree: the numpy way, said once
                refused(f"device {name!r}", error)
                self.compiled_guard = self.compiled_readings = self.compiled_unchecked = None
        # cycles whose read kept old values (a frame that came late): counted, the first ones kept
        self.stale_seen = self.stale_cycles = self.stale_run = self.stale_longest = 0
        self.stale_last = -2
        self.stale_first = np.zeros(STALE_CYCLES_KEPT, dtype=np.int64)  # allocated once: nothing in the loop

    def send(self, task: str, cycle: int) -> None:
        compiled = self.compiled_guard
        if compiled is not None:
            if compiled.apply() >= 0:  # a non-finite command: the reference names it in the fault it raises
                self.guard.apply(self.u, task, cycle)
            self.device.write(self.guard.out)
            return
        for source, target in self.command_copies:
            np.copyto(target, source)
        self.device.write(self.guard.apply(self.u, task, cycle))

    def receive(self, task: str, cycle: int) -> None:
        self.device.read(self.y)
        compiled = self.compiled_readings
        if compiled is not None:
            if compiled.run() >= 0:  # a non-finite reading: the reference names it in the fault it raises
                self.check_readings(task, cycle)
            if self.compiled_unchecked is not None:
                self.compiled_unchecked.run()
            return
        for source, target in self.reading_copies:
            np.copyto(target, source)
        self.check_readings(task, cycle)

    def check_readings(self, task: str, cycle: int) -> None:
        """A fault naming the first reading that is not finite (and crosses a connection that does not allow it)."""
        for start, values, finite in self.checked_readings:
            np.isfinite(values, out=finite)
            if np.count_nonzero(finite) != len(finite):
                index = int(np.argmin(finite))
                raise fault(task, cycle, self.reading_labels[start + index],
                            f"reading {float(values[index])!r} is not finite; the task did not step with it "
                            "(allow_nonfinite = true on the connection lets it through)")

    def note_stale(self, cycle: int) -> None:
        """This cycle's read kept old values: count the cycle, keep it among the first, and the run
        of cycles in a row that did (the lag: how many cycles old the values the task used were)."""
        self.stale_seen = self.device.stale_reads
        if self.stale_cycles < STALE_CYCLES_KEPT:
            self.stale_first[self.stale_cycles] = cycle
        self.stale_cycles += 1
        self.stale_run = self.stale_run + 1 if cycle == self.stale_last + 1 else 1
        self.stale_last = cycle
        self.stale_longest = max(self.stale_longest, self.stale_run)

    def stale_report(self) -> dict[str, object]:
        """What summary.json says of the device's stale reads (``devices.NAME``)."""
        device = self.device
        return {"kind": device.kind or type(device).__name__, "stale_reads": device.stale_reads,
                "stale_cycles": self.stale_cycles, "longest_lag_cycles": self.stale_longest,
                "first_stale_cycles": self.stale_first[:min(self.stale_cycles, STALE_CYCLES_KEPT)].tolist(),
                "stale_reads_by_source": device.stale_sources(),
                **self.guard.counts(device.command_names())}


class ScopePin:
    """A GPIO line that shows a task's cycles on an oscilloscope (a GPIO device's ``scope_pin``):
    toggled at every release (``toggle``), or high while ``step()`` runs (``step``). The task's
    devices drive it, first thing at the release and around the step; one ioctl per edge on the
    line request its device holds, with a buffer made once. A failed write of a diagnostic pin
    never stops the loop."""

    def __init__(self, fd: int, request: int, bit: int, mode: int) -> None:
        self.fd, self.request, self.mask = fd, request, 1 << bit
        self.toggles = mode == 1  # 1: toggle at every release, 2: high during step
        self.level = 0
        self.values = bytearray(GPIO_V2_LINE_VALUES.size)

    def _set(self, high: int) -> None:
        GPIO_V2_LINE_VALUES.pack_into(self.values, 0, self.mask if high else 0, self.mask)
        try:
            rt.ioctl(self.fd, self.request, self.values, "GPIO_V2_LINE_SET_VALUES_IOCTL")
        except OSError:
            pass  # a diagnostic pin: the loop goes on without it

    def at_release(self) -> None:
        if self.toggles:
            self.level ^= 1
            self._set(self.level)

    def before_step(self) -> None:
        if not self.toggles:
            self.level = 1
            self._set(1)

    def after_step(self) -> None:
        if not self.toggles:
            self.level = 0
            self._set(0)

    def stop(self) -> None:
        """Low, if a step that raised left it high: an edge only where there is one (a scope, or a
        test counting the pin's values, sees exactly one rise and one fall per step)."""
        if not self.toggles and self.level:
            self.after_step()


class TaskDevices:
    """The devices one task owns. ``bool(devices)`` is False when it owns none."""

    def __init__(self, task: str, period_ns: int, wirings: Sequence[DeviceWiring],
                 task_u: FloatVector, task_y: FloatVector, sent: FloatVector | None = None) -> None:
        """``sent``: where the commands each device was sent go, devices in order (the task records
        them after its ``u``: ``TaskWiring.sent``); None: nowhere but the guards."""
        self.task = task
        self.sources = {w.device.name: w.source for w in wirings}
        offsets = np.cumsum([0, *(w.device.n_inputs for w in wirings)]).tolist()
        self.slots = [_Slot(w, period_ns, task_u, task_y,
                            None if sent is None else sent[offsets[i]:offsets[i + 1]])
                      for i, w in enumerate(wirings)]
        self.let = [slot for slot, w in zip(self.slots, wirings, strict=True) if w.io == "let"]
        self.immediate = [slot for slot, w in zip(self.slots, wirings, strict=True) if w.io == "immediate"]
        self.may_be_stale = [slot for slot in self.slots if slot.device.may_read_stale()]
        self.configured: list[_Slot] = []
        self.active = False
        self.scope: ScopePin | None = None
        """The scope pin of the first device that has one, driven from activate() on."""
        self.problems: list[str] = []
        """What went wrong while stopping (the task reports it; the run's summary lists it)."""

    def __bool__(self) -> bool:
        return bool(self.slots)

    # --- before T0 --------------------------------------------------------------------------------
    def configure(self) -> None:
        """Open and check every device, then write its safe values (before T0); a failure closes
        those already open."""
        for slot in self.slots:
            device = slot.device
            try:
                device.configure()
                self.configured.append(slot)
                device.write_safe(slot.guard.safe_values())  # held safe until T0 (where the rate limit starts)
            except Exception as error:
                if slot not in self.configured:
                    try:
                        device.close()  # let go of whatever the half-done configure opened
                    except Exception:  # the configure error is the one to report
                        pass
                self.stop()
                if isinstance(error, DeviceError):
                    raise type(error)(device.name, self.sources[device.name], error.key, error.problem) from None
                raise DeviceError(device.name, self.sources[device.name], "",
                                  f"configure failed: {type(error).__name__}: {error}") from None

    def activate(self, t0_ns: int = 0, period_ns: int = 0) -> None:
        """At T0: enable the outputs (the first write follows at once), and the scope pin. Each
        device is told T0 and the period first (``period_ns`` 0: not known, a twin's run)."""
        self.active = True
        for slot in self.configured:
            if period_ns:
                slot.device.timeline(t0_ns, period_ns)
            slot.device.activate()
        pin = self.scope_output()
        self.scope = ScopePin(*pin) if pin is not None else None

    def scope_output(self) -> tuple[int, int, int, int] | None:
        """The scope pin of the first device that has one (a GPIO device's ``scope_pin``): (line request fd,
        its SET_VALUES ioctl number, the pin's bit, mode 1 toggle / 2 high during step)."""
        for slot in self.configured:
            scope = getattr(slot.device, "scope_output", None)
            pin: tuple[int, int, int, int] | None = scope() if scope is not None else None
            if pin is not None:
                return pin
        return None

    # --- every cycle ------------------------------------------------------------------------------
    def at_release(self, cycle: int) -> None:
        scope = self.scope
        if scope is not None:
            scope.at_release()  # first: the edge shows the wake-up, not the devices' I/O after it
        try:  # (a try costs nothing until it catches)
            for slot in self.let:  # the commands that hold from this release (computed by the job before)
                slot.send(self.task, cycle)
            for slot in self.slots:
                slot.receive(self.task, cycle)
        except DeviceFault as error:  # not the step: the fault report says where it happened
            error.phase = RELEASE_PHASE
            raise
        for slot in self.may_be_stale:  # devices that keep old values (on_missing = "stale") rather than fail
            if slot.device.stale_reads != slot.stale_seen:
                slot.note_stale(cycle)
        if scope is not None:
            scope.before_step()  # last: high for exactly the step

    def after_step(self, cycle: int) -> None:
        if self.scope is not None:
            self.scope.after_step()
        try:
            for slot in self.immediate:
                slot.send(self.task, cycle)
        except DeviceFault as error:
            error.phase = AFTER_STEP_PHASE
            raise

    def stale_report(self) -> dict[str, dict[str, object]]:
        """Per device: its stale reads, the cycles that had them (the first ones), the longest lag."""
        return {slot.device.name: slot.stale_report() for slot in self.slots}

    # --- every way out ----------------------------------------------------------------------------
    def stop(self) -> None:
        """Safe values to every configured device, then deactivate and close it. Never raises:
        each device gets its turn whatever the others do (see ``problems``)."""
        if self.scope is not None:
            self.scope.stop()  # low, if a step that raised left it high
            self.scope = None
        for slot in self.configured:
            device = slot.device
            for action in ("write_safe", "deactivate", "close"):
                try:
                    if action == "write_safe":
                        device.write_safe(slot.guard.safe_values())
                    elif action == "deactivate":
                        if self.active:
                            device.deactivate()
                    else:
                        device.close()
                except Exception as error:  # every device must get its safe values
                    self.problems.append(f"device {device.name!r}: {action} failed: {type(error).__name__}: {error}")
        self.configured = []
        self.active = False


def safe_for_dead_task(task: str, wirings: Sequence[DeviceWiring], why: str) -> list[str]:
    """In the supervisor, when ``task``'s process died without writing its devices' safe values
    (``why``: killed by SIGKILL, …): each device writes them from outside where its interface
    allows (:meth:`Device.write_safe_for_dead_task`). Never raises; returns the notes saying what
    was done for each device, or that only its own watchdog protects it."""
    notes = []
    for wiring in wirings:
        device = wiring.device
        safe = np.array([limit.safe for limit in wiring.limits], dtype=np.float64)
        try:
            done = device.write_safe_for_dead_task(safe)
        except Exception as error:
            done, failed = "", f" (writing them from the supervisor failed: {type(error).__name__}: {error})"
        else:
            failed = ""
        what = (f"the supervisor {done}" if done else
                f"nothing the supervisor can write{failed}: only the device's own heartbeat timeout protects it")
        notes.append(f"task {task} {why} before its device {device.name!r} ({device.kind or type(device).__name__}) "
                     f"got its safe values: {what}")
    return notes


def release_after_dead_task(wirings: Sequence[DeviceWiring]) -> None:
    """At the end of the run: let go of what :func:`safe_for_dead_task` holds (GPIO lines)."""
    for wiring in wirings:
        try:
            wiring.device.close()
        except Exception:
            pass  # the lines go with the supervisor's process anyway


__all__ = ["DeviceFault", "DeviceWiring", "TaskDevices", "release_after_dead_task", "safe_for_dead_task"]
