"""A device: hardware a task reads and writes every cycle, behind a narrow seam.

A driver is a :class:`Device` subclass. Its lifecycle is named as ros2_control names it:

=================  ==========================  ============================================
call               where, when                 what the driver does
=================  ==========================  ============================================
``__init__``       app loading (supervisor)    keep the validated settings; set the sizes;
                                               open nothing (the object travels to the task
                                               process by pickle)
``check()``        supervisor, before any      does the interface exist, may this user open
                   process starts              it? raise :class:`DeviceError` with the fix
``configure()``    owner task's process,       open and check (a wrong answer from the
                   before T0                   device is a :class:`DeviceError`)
``activate()``     at T0                       enable outputs (power on, brakes off)
``write(u)``       every cycle                 send the commands ``u`` (already clamped,
                                               rate limited and finite)
``read(y)``        every cycle                 fill ``y`` with what the device reports
``write_safe(u)``  on every way out            send the safe values ``u`` (default: write)
``deactivate()``   at the end                  disable outputs
``close()``        at the end                  let go of the interface
``write_safe_for_  supervisor, when the owner  write the safe values from outside (CAN: the
dead_task(u)``     task was killed (SIGKILL)   safe frames; GPIO: the lines at their safe
                                               levels), or say it cannot
=================  ==========================  ============================================

Sizes: ``n_inputs`` is how many values the device *writes* (its ``u``: commands),
``n_outputs`` how many it *reads* (its ``y``: readings), as for a task. The app wires them
with the same connections as tasks (``motor.y[0]`` → a task input, a task output →
``motor.u[0]``).

``read`` and ``write`` run inside the real-time loop: no allocation, no logging, a bounded
wait at most (a timeout that raises :class:`DeviceFault`). Import the driver's library
(``gpiod``, ``serial``, …) in ``check``/``configure``, not at the module's top: an app
with devices must still load, and simulate with its twins, where the library is missing.

A driver declares its settings in ``settings`` (name → :class:`Setting`): the app file's
``[devices.NAME]`` table is checked against it (types, required keys, unknown keys
rejected) before ``__init__`` sees them.
"""

from __future__ import annotations

import importlib
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from rtloop.errors import DeviceError, DeviceFault, DeviceMismatch, DeviceNotReady
from rtloop.text import shorten

__all__ = ["KINDS", "Claim", "CommandLimit", "Device", "DeviceError", "DeviceFault", "Setting", "check_claims",
           "device_class"]

FloatVector = npt.NDArray[np.float64]

KINDS: dict[str, str] = {
    "gpio": "rtloop.io.gpio:GpioDevice",
    "can": "rtloop.io.can:CanDevice",
    "spi": "rtloop.io.spi:SpiDevice",
    "serial": "rtloop.io.serial:SerialDevice",
    "i2c": "rtloop.io.i2c:I2cDevice",
    "dynamixel": "rtloop.io.servos.bus:DynamixelBus",
    "feetech": "rtloop.io.servos.bus:FeetechBus",
    "ethercat": "rtloop.io.drives.ethercat:EthercatDevice",
    "canopen402": "rtloop.io.drives.canopen:Canopen402Device",
}
"""Device kinds → their driver class (``module:Class``), imported when an app uses the kind.
A driver adds itself by living at that path; ``kind = "package.module:Class"`` names any
other :class:`Device` subclass."""

IO_MODES = ("let", "immediate")
"""``let``: the commands of the job released at t are written at t + P (default);
``immediate``: right after ``step``."""

MAX_SETTING_MAGNITUDE = 1e12
"""No number in a device's settings is larger (a GHz clock is 1e9 Hz): beyond it is a typo
(``1e308``), and it would overflow where a driver turns it into nanoseconds or a C integer."""
HOUR_MS = 3_600_000
"""The longest wait a device setting may ask for, in ms: more than an hour is a typo."""

_REQUIRED = object()
_TYPE_NAMES = {str: "a string", int: "an integer", float: "a number", bool: "true or false",
               list: "an array", dict: "a table"}


@dataclass(frozen=True, slots=True)
class Setting:
    """One key of a driver's settings: its type, its default (none: required), a check."""

    type: type
    """``str``, ``int``, ``float`` (an integer is accepted), ``bool``, ``list`` or ``dict``."""
    default: Any = _REQUIRED
    """Value when the key is absent; without one the key is required."""
    doc: str = ""
    """What the setting means, with its unit (shown by errors)."""
    check: Callable[[Any], str | None] | None = None
    """Returns what is wrong with a value (one phrase), or None when it is fine."""
    at_most: float = MAX_SETTING_MAGNITUDE
    """A number's largest value (its unit makes one obvious: ``HOUR_MS`` for a timeout in ms);
    every number is finite and at least ``-MAX_SETTING_MAGNITUDE`` too."""
    is_path: bool = False
    """A file's path: in an app file a relative one is taken from the app file's folder, as
    every path there is (a feed, a module); in Python, from the current folder."""

    @property
    def required(self) -> bool:
        return self.default is _REQUIRED


@dataclass(frozen=True, slots=True)
class CommandLimit:
    """What the framework enforces on one command before the driver sees it."""

    min: float
    """Lowest value sent; lower commands are clamped to it."""
    max: float
    """Highest value sent; higher commands are clamped to it."""
    safe: float
    """Written on every way a run ends (and the start of the rate limit at T0)."""
    rate_per_s: float = math.inf
    """Largest change per second; a faster command is followed at this rate (inf: no limit)."""

    def problem(self) -> str | None:
        """What is wrong with these limits (one phrase), or None."""
        values = (self.min, self.max, self.safe)
        if not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in values):
            return f"min, max and safe must be finite numbers, got {self.min!r}, {self.max!r}, {self.safe!r}"
        for key, value in (("min", self.min), ("max", self.max), ("safe", self.safe)):
            problem = number_problem(value)
            if problem:
                return f"{key} {problem}"
        if not self.min <= self.safe <= self.max:
            return f"need min ≤ safe ≤ max, got min {self.min!r}, safe {self.safe!r}, max {self.max!r}"
        rate = self.rate_per_s
        if isinstance(rate, bool) or not isinstance(rate, int | float) or not rate > 0:
            return f"rate_per_s must be a number > 0 (or absent: no limit), got {rate!r}"
        return None


@dataclass(frozen=True, slots=True)
class Claim:
    """Something only one device of an app may hold: two holders are refused when the app loads
    (two shared holders are fine).

    Two devices sending one CAN id on one bus would interleave their commands to one drive
    (each overwriting the other every half period); a device receiving an id another sends
    would read those commands as its readings. No single device can see either."""

    resource: tuple[Any, ...]
    """Claims of equal resources clash, e.g. ``("can", "vcan0", 0x200)``."""
    key: str
    """The device's setting that claims it, as errors name it: ``send[0].id``."""
    clash: str
    """The problem, followed in the error by the other holder's role and key:
    ``frame id clash: 0x200 on vcan0 is also`` (``sent by devices.drive.send[0]``)."""
    role: str = "held"
    """What the holder does with it, for the other's error: ``sent``, ``received``."""
    shared: bool = False
    """Shared claims do not clash with each other (two devices receiving one CAN id), only with another kind."""


class Device(ABC):
    """Base class of drivers (and of the twin stand-in). See the module's docstring."""

    kind: ClassVar[str] = ""
    """The ``kind`` the app file names it by (``gpio``, ``can``, …)."""
    settings: ClassVar[Mapping[str, Setting]] = {}
    """The keys its ``[devices.NAME]`` table may hold, besides the common ones."""

    n_inputs: int = 0
    """Values it writes each cycle (its ``u``: commands)."""
    n_outputs: int = 0
    """Values it reads each cycle (its ``y``: readings)."""
    input_names: tuple[str, ...] | None = None
    """Names of the commands (used in limits and messages); default ``u0``, ``u1``, …"""
    output_names: tuple[str, ...] | None = None
    """Names of the readings; default ``y0``, ``y1``, …"""
    safe_write_is_exchange: ClassVar[bool] = False
    """Whether ``write_safe`` is an exchange the device answers, moving its own state on as a
    cycle's would (a serial request: the driver steps its model; an SPI transfer). Its twin then
    steps on the safe values too — at configure, before T0, and on the way out — so it sees every
    exchange the device sees and a run stays in step with its simulation from the first row."""
    stale_reads: int = 0
    """Reads that kept the last good values instead of failing (a CAN frame that did not come in
    time, an SPI answer with a bad CRC): a driver that may read stale counts them here; the task
    reports them per cycle in summary.json (``devices``)."""

    def __init__(self, name: str, **settings: Any) -> None:
        self.name = name
        self.config = settings

    # --- description (supervisor) ------------------------------------------------------------
    def default_limits(self) -> dict[str, CommandLimit]:
        """Limits a driver knows for its commands (a GPIO line: 0..1, safe 0); the app's override."""
        return {}

    def default_twin(self) -> Any:
        """The twin a driver brings for itself (a Runnable, like an app's ``twin``), or None: the
        servo buses run their own code against their servo model, a drive device its emulated drives."""
        return None

    def check(self) -> None:
        """Before any process starts: the interface exists and this user may open it."""

    def period_problem(self, period_ns: int) -> tuple[str, str] | None:
        """A setting that does not fit the period of the task that owns the device, as
        ``(key, problem)`` (an EtherCAT device's ``lost_frames_max`` that would leave the drives
        unwatched past their watchdog); None when it fits. Asked as the app is built."""
        return None

    def claims(self) -> tuple[Claim, ...]:
        """What no other device of the app may hold too (a CAN id this device sends on its bus)."""
        return ()

    # --- lifecycle (owner task's process) -------------------------------------------------------
    def configure(self) -> None:
        """Open the interface and check the device answers (before T0)."""

    def timeline(self, t0_ns: int, period_ns: int) -> None:
        """T0 and the period (CLOCK_MONOTONIC, ns), told just before :meth:`activate`: for a device
        whose hardware keeps time on rtloop's releases itself (EtherCAT distributed clocks' SYNC0)."""

    def activate(self) -> None:
        """At T0, before the first write: enable the outputs."""

    @abstractmethod
    def read(self, y: FloatVector) -> None:
        """Fill ``y`` (length ``n_outputs``) with what the device reports now."""

    @abstractmethod
    def write(self, u: FloatVector) -> None:
        """Send ``u`` (length ``n_inputs``): finite, clamped and rate limited already."""

    def write_safe(self, u: FloatVector) -> None:
        """Send the safe values ``u`` (a driver may do more: a stop frame, a brake line)."""
        self.write(u)

    def deactivate(self) -> None:
        """At the end, after the safe values: disable the outputs."""

    # --- when the owner task's process is dead (supervisor) -------------------------------------
    def write_safe_for_dead_task(self, u: FloatVector) -> str:
        """The owner task's process died without writing the safe values (SIGKILL, a crash in C):
        write ``u`` from the supervisor's process if the interface lets another process do it.

        Returns what was done (one phrase for summary.json), or "" when nothing can be done from
        outside (the device's own heartbeat timeout must then protect the machine). The kernel
        has closed the dead process's file descriptors, so its lines and sockets are free. Runs
        once, outside the real-time loop: it may allocate and open what it needs."""
        return ""

    def close(self) -> None:
        """Let go of the interface (also after a failed configure)."""

    # --- stale reads ----------------------------------------------------------------------------
    def may_read_stale(self) -> bool:
        """Whether a read may keep old values and count them (``on_missing = "stale"``) instead of failing."""
        return False

    def stale_sources(self) -> dict[str, int]:
        """Stale reads per source (a received frame) where the driver tells them apart."""
        return {}

    def run_notes(self) -> list[str]:
        """Sentences for the run's summary and console on how the device ran (which slaves ran on
        distributed clocks); asked at the end of the run."""
        return []

    # --- names ----------------------------------------------------------------------------------
    def command_names(self) -> tuple[str, ...]:
        return tuple(self.input_names or (f"u{i}" for i in range(self.n_inputs)))

    def reading_names(self) -> tuple[str, ...]:
        return tuple(self.output_names or (f"y{i}" for i in range(self.n_outputs)))


def device_class(kind: str, device: str, source: str) -> type[Device]:
    """The driver class of ``kind`` (a registered kind or ``package.module:Class``)."""
    target = KINDS.get(kind, kind)
    module_name, colon, class_name = target.partition(":")
    if not colon or not class_name.isidentifier() or not all(p.isidentifier() for p in module_name.split(".")):
        raise DeviceError(device, source, "kind", f"{kind!r}; expected one of {sorted(KINDS)} "
                          "or 'package.module:Class' naming a Device subclass")
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        missing = "no driver yet" if kind in KINDS else "cannot import it"
        raise DeviceError(device, source, "kind", f"{kind!r}: {missing} ({module_name}: {error})") from None
    cls = getattr(module, class_name, None)
    if not isinstance(cls, type) or not issubclass(cls, Device):
        raise DeviceError(device, source, "kind", f"{target} is not an rtloop Device subclass")
    return cls


def build_device(kind: str | type[Device], name: str, settings: Mapping[str, Any], source: str) -> Device:
    """Check ``settings`` against the driver's schema (unknown keys rejected), then build it."""
    cls = device_class(kind, name, source) if isinstance(kind, str) else kind
    values: dict[str, Any] = {}
    for key, value in settings.items():
        setting = cls.settings.get(key)
        if setting is None:
            keys = sorted(cls.settings)
            raise DeviceError(name, source, key, f"unknown setting of a {cls.kind or cls.__name__} device; "
                              f"expected one of {keys}")
        values[key] = _checked(name, source, key, setting, value)
    for key, setting in cls.settings.items():
        if key not in values:
            if setting.required:
                raise DeviceError(name, source, key, f"missing: {setting.doc or 'required'}")
            values[key] = setting.default
    try:
        device = cls(name, **values)
    except DeviceError as error:  # a driver checks its settings without knowing the app file: name it
        raise DeviceError(name, error.source or source, error.key, error.problem) from None
    except (ValueError, TypeError) as error:
        raise DeviceError(name, source, "", f"{type(error).__name__}: {error}") from None
    for side in ("n_inputs", "n_outputs"):
        count = getattr(device, side)
        if not isinstance(count, int) or isinstance(count, bool) or not 0 <= count <= 1 << 16:
            raise DeviceError(name, source, "", f"{type(device).__name__}.{side} must be an integer 0..65536, "
                              f"got {count!r}")
    return device


def check_claims(devices: list[Device], source: str) -> None:
    """Refuse two devices holding one :class:`Claim` (the later one is named, with the earlier's key)."""
    holders: dict[tuple[Any, ...], list[tuple[Device, Claim]]] = {}
    for device in devices:
        for claim in device.claims():
            held = holders.setdefault(claim.resource, [])
            for other, first in held:
                if other is not device and not (claim.shared and first.shared):
                    raise DeviceError(device.name, source, claim.key,
                                      f"{claim.clash} {first.role} by devices.{other.name}.{first.key}")
            held.append((device, claim))


def check_device(device: Device, source: str) -> None:
    """``device.check()``, its failures as a :class:`DeviceError` naming the app file."""
    try:
        device.check()
    except DeviceMismatch as error:  # the device answered, but it is not the one declared: bad input
        raise DeviceMismatch(device.name, source, error.key, error.problem) from None
    except DeviceError as error:
        raise DeviceNotReady.of(DeviceError(device.name, source, error.key, error.problem)) from None
    except Exception as error:
        raise DeviceNotReady(device.name, source, "", f"check failed: {type(error).__name__}: {error}") from None


def _checked(device: str, source: str, key: str, setting: Setting, value: Any) -> Any:
    expected = setting.type
    ok = isinstance(value, expected) and not (expected in (int, float) and isinstance(value, bool))
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        value, ok = float(value), True
    if not ok:
        what = f" ({setting.doc})" if setting.doc else ""  # bus = "/dev/i2c-1": "the I2C bus number (/dev/i2c-N)"
        raise DeviceError(device, source, key, f"expected {_TYPE_NAMES.get(expected, expected.__name__)}{what}, "
                          f"got {shorten(value, 60)}")
    if expected in (int, float):
        problem = number_problem(value, setting.at_most)
        if problem:
            raise DeviceError(device, source, key, problem)
    if setting.check is not None:
        problem = setting.check(value)
        if problem:
            raise DeviceError(device, source, key, problem)
    return value


def positive(value: float) -> str | None:
    """A setting's check: a number above 0."""
    return None if value > 0 else f"must be > 0, got {value!r}"


def number_problem(value: float, at_most: float = MAX_SETTING_MAGNITUDE) -> str | None:
    """What is wrong with a number of a device's settings (one phrase), or None: not finite, or absurd."""
    if not math.isfinite(value):
        return f"must be finite, got {value!r}"
    if value > at_most:
        return f"must be at most {_plain(at_most)}, got {shorten(value, 30)}"
    if value < -MAX_SETTING_MAGNITUDE:
        return f"must be at least {_plain(-MAX_SETTING_MAGNITUDE)}, got {shorten(value, 30)}"
    return None


def _plain(number: float) -> str:
    """3600000 as 3600000, 1e12 as 1e+12: as a person would type it in the app file."""
    return str(int(number)) if float(number).is_integer() and abs(number) < 1e7 else f"{number:g}"


def fault(task: str, cycle: int, where: str, problem: str) -> DeviceFault:
    """A device fault naming the task, the cycle and the device signal (``motor.u[0] (voltage)``)."""
    return DeviceFault(f"task {task!r}, cycle {cycle}: {where}: {problem}")
