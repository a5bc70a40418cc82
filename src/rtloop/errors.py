"""Exceptions raised by rtloop.

Every rtloop error derives from :class:`RtloopError` and also from the built-in
exception it resembles, so ``except ValueError`` keeps working for callers that do
not know rtloop. Each survives pickling (a task process, a ``multiprocessing`` pool or a
notebook's worker hands it on whole): those built from several fields say how with
``__reduce__``.

Exit codes of the ``rtloop`` command follow one rule (``cli/main.py:exit_code_for``):
2 for bad input (an :class:`AppError`, any ``ValueError``/``LookupError``/
``PermissionError``, a missing optional package), 1 for a run that failed
(:class:`TaskFailed` and every other error), 130 for Ctrl-C.
"""

from __future__ import annotations


class RtloopError(Exception):
    """Base class of every error raised by rtloop."""


class AppError(RtloopError, ValueError):
    """An application is wired or configured wrongly (detected before anything runs)."""


class AppFileError(AppError):
    """An app file (TOML) is malformed: names the file, the key and what was expected."""

    def __init__(self, path: str, key: str, problem: str) -> None:
        self.path = path
        self.key = key
        self.problem = problem
        where = f"{path}: {key}" if key else str(path)
        super().__init__(f"{where}: {problem}")

    def __reduce__(self) -> tuple[type, tuple[str, str, str]]:
        return type(self), (self.path, self.key, self.problem)  # pickled with what builds it again


class ConnectionSizeError(AppError):
    """The two ends of a connection or port have different sizes."""


class LibcError(RtloopError, OSError):
    """A libc call failed; names the call and its errno."""

    def __init__(self, call: str, errno_value: int, hint: str = "") -> None:
        import os

        self.call = call
        message = f"{call} failed: {os.strerror(errno_value)} (errno {errno_value})"
        if hint:
            message += f" — {hint}"
        super().__init__(errno_value, message)
        self.message = message
        self.hint = hint

    def __reduce__(self) -> tuple[type[LibcError], tuple[str, int | None, str]]:
        return type(self), (self.call, self.errno, self.hint)

    def __str__(self) -> str:
        return self.message


FAULTS_SAID_IN_FULL = ("DeviceFault", "NonFiniteOutput", "ModelError", "FmuError")
"""Faults rtloop raises itself, naming task, cycle and signal (a model's error: the model and what it said):
no traceback on the console."""


class TaskFailed(RtloopError, RuntimeError):
    """A task stopped because its runnable raised or its process died.

    Attributes:
        task: name of the task.
        cycle: cycle number at which it failed (``None`` if before the first cycle).
        phase: ``"loading"`` (its class, in the task process), ``"prerun"``, ``"release"`` (its devices'
            exchange before the step), ``"step"``, ``"device write after step"``, ``"postrun"`` or ``"process"``.
        traceback_text: the original traceback, formatted in the task process.
    """

    def __init__(
        self, task: str, cycle: int | None, phase: str, reason: str, traceback_text: str = ""
    ) -> None:
        self.task = task
        self.cycle = cycle
        self.phase = phase
        self.reason = reason
        self.traceback_text = traceback_text
        at = f" at cycle {cycle}" if cycle is not None else ""
        super().__init__(f"task {task!r} failed in {PHASE_WORDS.get(phase, phase)}{at}: {reason}")

    def __reduce__(self) -> tuple[type, tuple[str, int | None, str, str, str]]:
        return type(self), (self.task, self.cycle, self.phase, self.reason, self.traceback_text)

    @property
    def said_in_full(self) -> bool:
        """Whether the message says all there is: a fault rtloop itself found (a device's timeout, a
        NaN command or reading, a NaN output) names task, cycle and signal; its traceback would show
        only rtloop's own code (summary.json keeps it; ``--debug`` prints it)."""
        return self.reason.partition(":")[0] in FAULTS_SAID_IN_FULL

    def to_json(self) -> dict[str, object]:
        return {
            "task": self.task,
            "cycle": self.cycle,
            "phase": self.phase,
            "reason": self.reason,
            "traceback": self.traceback_text,
        }


class DeadlineMissesExceeded(RtloopError, RuntimeError):
    """A task missed more consecutive deadlines than its ``max_consecutive_misses`` allows."""


class WatchdogExpired(RtloopError, RuntimeError):
    """A real-time task ran past its watchdog limit without sleeping (the kernel's RLIMIT_RTTIME
    told it with SIGXCPU): a step spinning at a real-time priority."""


class NonFiniteOutput(RtloopError, ValueError):
    """A NaN or infinite output was headed across a connection that does not allow it."""


class PortValueError(RtloopError, ValueError):
    """A value written to a port was rejected (wrong length, NaN/inf)."""


class StopRequested(RtloopError):
    """Raised by a runnable's ``step`` to stop the app in order (not a fault).

    A model that reached its end (an FMU's ``terminateSimulation``) raises it: the
    task publishes nothing for that step, runs ``postrun``, and the app stops with
    ``stopped_by`` naming the task and this reason.
    """


class DeviceError(AppError):
    """A device cannot be used as declared: a bad setting, a missing interface, no permission.

    Found before any task starts (the app file is checked, then each device is checked and
    configured before T0); names the device, the app file and the key.
    """

    def __init__(self, device: str, source: str, key: str, problem: str) -> None:
        self.device, self.source, self.key, self.problem = device, source, key, problem
        where = f"devices.{device}.{key}" if key else f"devices.{device}"
        super().__init__(f"{source}: {where}: {problem}")

    def __reduce__(self) -> tuple[type, tuple[str, str, str, str]]:
        return type(self), (self.device, self.source, self.key, self.problem)


class DeviceNotReady(DeviceError):
    """A device declared right that refused at start, as found then: its interface is not there (yet),
    it is busy or not ours to open, it did not answer at configure. ``rtloop run`` exits 3, not 2:
    the app file is fine, and a service retries it (a USB adapter that enumerates a second late, a
    drive powered after the computer)."""

    @classmethod
    def of(cls, error: DeviceError) -> DeviceError:
        """``error`` as found at start: not ready, unless it is a missing driver library or a device
        that answered as another than declared (bad input)."""
        if error.key == "kind" or isinstance(error, DeviceMismatch):  # retrying will not change them
            return error
        return cls(error.device, error.source, error.key, error.problem)


class DeviceMismatch(DeviceError):
    """A device that answered and is not what the app declares (a servo ID not on the bus, another
    model, a range outside its own limits; an EtherCAT slave of another vendor, product or revision,
    another count of slaves, a PDO mapping without an object the app needs): bad input, exit 2, not
    retried (a service retrying it would find the same device)."""


class DeviceFault(RtloopError, RuntimeError):
    """A device failed while the app ran (a read timed out, a non-finite command was refused).

    The task stops, every device of the app is put in its safe state; the message names the
    task, the cycle and the device's signal.
    """

    phase: str | None = None
    """Where in the cycle: :data:`RELEASE_PHASE` or :data:`AFTER_STEP_PHASE` (set by the task's devices)."""


RELEASE_PHASE = "release"
"""A task's phase: the devices' exchange at a release, before the step (the write of the commands the
step before computed, io = "let", then the read)."""
AFTER_STEP_PHASE = "device write after step"
"""A task's phase: the write of an ``io = "immediate"`` device's commands, right after the step."""
PHASE_WORDS = {RELEASE_PHASE: "the devices' write and read at the release, before the step,"}
"""How a phase reads in ``failed in …`` where its name alone would not say it."""


class NotRealTimeWarning(RuntimeWarning):
    """``rtloop.run`` ran a task without a real-time policy (no privileges): its timing is not real time.

    The run goes on (a laptop, a notebook); the summary's notes say it too. ``rtloop run`` prints
    its own WARNING line instead, so it silences this one.
    """
