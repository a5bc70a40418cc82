"""GPIO devices on the Linux GPIO character device (v2 uAPI), through libgpiod's ``gpiod`` >= 2.

    [devices.panel]
    kind = "gpio"
    chip = "gpiochip0"                  # or /dev/gpiochip0
    inputs = ["limit_left", "17"]       # line names, or offsets written as numbers
    outputs = ["enable", "brake"]
    scope_pin = "scope"                 # toggled at every release (scope_mode = "toggle")
    scope_mode = "toggle"               # or "step": high while step() runs
    estop = "estop"                     # an edge stops the app, safe states first
    estop_edge = "falling"              # "rising" | "falling" | "both" (the button's contact)

``gpiod`` requests the lines (by name or offset, with the kernel's own "line busy" answer);
every cycle then costs one ``ioctl`` on the request's file descriptor:
``GPIO_V2_LINE_SET_VALUES_IOCTL`` for all outputs together, ``GPIO_V2_LINE_GET_VALUES_IOCTL``
for all inputs together (gpiod's ``set_value`` builds dictionaries on every call). Where
``io/_devio.c`` was built (``io/compiled.py``), a cycle's write and read are one C call each
(``GpioLines``: the bits packed, the ioctl, the bits unpacked, the E-stop's pending edge);
``write`` and ``read`` below are their Python reference, the same bits either way.

A command ≥ 0.5 drives its line active; a reading is 0.0 or 1.0. The safe value of every
output is 0 (inactive) unless the app says otherwise.

E-stop: the line is requested with edge detection; every ``read`` asks the kernel (one
``poll`` with no wait) whether an edge came. One did: the task writes every device's safe
values and the app stops, and the summary names the edge's kernel timestamp (CLOCK_MONOTONIC,
the clock of rtloop's timeline). An E-stop already pressed at start refuses to start.
This is a software stop: the machine's hardware emergency stop (safe torque off) stays wired
on its own.
"""

from __future__ import annotations

import os
import select
from typing import Any, ClassVar

from rtloop.errors import DeviceError, StopRequested
from rtloop.io.bytelayout import FloatView
from rtloop.io.compiled import devio
from rtloop.io.device import CommandLimit, Device, FloatVector, Setting
from rtloop.io.kernel import (
    GPIO_V2_LINE_EVENT,
    GPIO_V2_LINE_EVENT_RISING_EDGE,
    GPIO_V2_LINE_GET_VALUES_IOCTL,
    GPIO_V2_LINE_SET_VALUES_IOCTL,
    GPIO_V2_LINE_VALUES,
)
from rtloop.linux import rt

__all__ = ["EmergencyStop", "GpioDevice"]

SCOPE_MODES = ("toggle", "step")
EDGES = ("rising", "falling", "both")


class EmergencyStop(StopRequested):
    """An E-stop edge: the app stops in order, safe states first."""

    def __init__(self, device: str, line: str, edge: str, timestamp_ns: int) -> None:
        self.device, self.line, self.edge, self.timestamp_ns = device, line, edge, timestamp_ns
        super().__init__(f"E-stop: {edge} edge on line {line!r} of device {device!r} "
                         f"at {timestamp_ns} ns (CLOCK_MONOTONIC, kernel timestamp)")

    def to_json(self) -> dict[str, Any]:
        return {"device": self.device, "line": self.line, "edge": self.edge, "edge_ns": self.timestamp_ns}


def _lines(value: list[Any]) -> str | None:
    for line in value:
        if isinstance(line, bool) or not isinstance(line, str | int) or line == "":
            return f"expected line names or offsets, got {line!r}"
        if isinstance(line, int) and not 0 <= line <= 0xFFFFFFFF:  # the kernel's offsets are u32
            return f"a line offset is 0..4294967295, got {line!r}"
    if len({str(line) for line in value}) != len(value):
        return "a line is named twice"
    return None


def _one_of(choices: tuple[str, ...]) -> Any:
    return lambda value: None if value in choices else f"expected one of {', '.join(choices)}, got {value!r}"


def line_id(line: str | int) -> str | int:
    """A line as gpiod takes it: an offset (int, or a string of digits) or a name."""
    if isinstance(line, str) and line.isdigit():
        return int(line)
    return line


def chip_path(chip: str) -> str:
    return chip if chip.startswith("/") else f"/dev/{chip}"


class GpioDevice(Device):
    """Input and output lines of one GPIO chip, a scope pin and an E-stop input."""

    kind: ClassVar[str] = "gpio"
    settings: ClassVar[dict[str, Setting]] = {
        "chip": Setting(str, doc="the GPIO chip (gpiochip0 or /dev/gpiochip0)"),
        "inputs": Setting(list, [], "lines read every cycle (names, or offsets)", _lines),
        "outputs": Setting(list, [], "lines written every cycle (names, or offsets)", _lines),
        "scope_pin": Setting(str, "", "a line toggled at every release, to see the timing on a scope"),
        "scope_mode": Setting(str, "toggle", "toggle: at every release; step: high while step() runs",
                              _one_of(SCOPE_MODES)),
        "estop": Setting(str, "", "an input whose edge stops the app (safe states first)"),
        "estop_edge": Setting(str, "falling", "which edge of the E-stop line stops: rising, falling, both",
                              _one_of(EDGES)),
        "active_low": Setting(list, [], "lines whose active level is low (names or offsets)", _lines),
    }

    def __init__(self, name: str, **settings: Any) -> None:
        super().__init__(name, **settings)
        self.chip: str = settings["chip"]
        self.inputs = [line_id(line) for line in settings["inputs"]]
        self.outputs = [line_id(line) for line in settings["outputs"]]
        self.scope_pin = line_id(settings["scope_pin"]) if settings["scope_pin"] else None
        self.scope_mode: str = settings["scope_mode"]
        self.estop = line_id(settings["estop"]) if settings["estop"] else None
        self.estop_edge: str = settings["estop_edge"]
        self.active_low = {str(line) for line in settings["active_low"]}
        named = [*map(str, self.inputs), *map(str, self.outputs),
                 *([str(self.scope_pin)] if self.scope_pin is not None else []),
                 *([str(self.estop)] if self.estop is not None else [])]
        twice = sorted({line for line in named if named.count(line) > 1})
        if twice:
            raise DeviceError(name, "", "outputs", f"line {twice[0]!r} is used twice in this device")
        self.n_inputs, self.n_outputs = len(self.outputs), len(self.inputs)
        self.input_names = tuple(str(line) for line in self.outputs)
        self.output_names = tuple(str(line) for line in self.inputs)
        self._requests: list[Any] = []
        self._lines: Any = None  # the cycle in C (io/_devio.c GpioLines), once configured
        self._u, self._y = FloatView(), FloatView()

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_requests": [], "_lines": None}

    def default_limits(self) -> dict[str, CommandLimit]:
        return {name: CommandLimit(min=0.0, max=1.0, safe=0.0) for name in self.command_names()}

    # --- supervisor ---------------------------------------------------------------------------
    def check(self) -> None:
        """The chip exists, this user may open it, every line exists and is free."""
        chip = self._open_chip()
        try:
            for key, line in self._declared():
                offset = self._offset(chip, key, line)
                info = chip.get_line_info(offset)
                if info.used:
                    by = f" by {info.consumer!r}" if info.consumer else ""
                    raise DeviceError(self.name, "", key, f"line {line!r} (offset {offset}) of {self.chip} is busy: "
                                      f"in use{by}")
        finally:
            chip.close()

    def _declared(self) -> list[tuple[str, str | int]]:
        return [*(("inputs", line) for line in self.inputs), *(("outputs", line) for line in self.outputs),
                *([("scope_pin", self.scope_pin)] if self.scope_pin is not None else []),
                *([("estop", self.estop)] if self.estop is not None else [])]

    def _open_chip(self) -> Any:
        try:
            import gpiod
        except ImportError:
            raise DeviceError(self.name, "", "kind", "GPIO needs libgpiod's Python binding: pip install "
                              "'gpiod>=2' (or rtloop[gpio])") from None
        path = chip_path(self.chip)
        if not os.path.exists(path):
            chips = sorted(name for name in os.listdir("/dev") if name.startswith("gpiochip"))
            found = f"chips here: {', '.join(chips)}" if chips else "this machine has no GPIO chip"
            raise DeviceError(self.name, "", "chip", f"no GPIO chip {path} ({found})")
        try:
            return gpiod.Chip(path)
        except PermissionError:
            raise DeviceError(self.name, "", "chip", f"no permission to open {path} (run as root, or add this "
                              "user to the group owning it, often 'gpio')") from None
        except OSError as error:
            raise DeviceError(self.name, "", "chip", f"cannot open {path}: {error.strerror or error}") from None

    def _offset(self, chip: Any, key: str, line: str | int) -> int:
        try:
            offset: int = chip.line_offset_from_id(line)
        except (OSError, ValueError):
            offset = -1
        if not 0 <= offset < chip.get_info().num_lines:
            raise DeviceError(self.name, "", key, f"no line {line!r} on {self.chip}")
        return offset

    # --- task process ---------------------------------------------------------------------------
    def configure(self) -> None:
        from gpiod import LineSettings
        from gpiod.line import Direction, Edge, Value

        chip = self._open_chip()
        self._requests = []
        try:
            consumer = f"rtloop:{self.name}"[:31]
            outputs = [*self.outputs, *([self.scope_pin] if self.scope_pin is not None else [])]
            self._out, out_offsets = self._request(chip, outputs, "outputs", consumer, lambda low: LineSettings(
                direction=Direction.OUTPUT, output_value=Value.INACTIVE, active_low=low))
            self._in, in_offsets = self._request(chip, self.inputs, "inputs", consumer, lambda low: LineSettings(
                direction=Direction.INPUT, active_low=low))
            edge = {"rising": Edge.RISING, "falling": Edge.FALLING, "both": Edge.BOTH}[self.estop_edge]
            self._estop, _ = self._request(chip, [self.estop] if self.estop is not None else [], "estop", consumer,
                                           lambda low: LineSettings(direction=Direction.INPUT, edge_detection=edge,
                                                                    active_low=low))
        except BaseException:
            self.close()
            raise
        finally:
            chip.close()
        self._scope_bit = _bit(self._out, out_offsets[-1]) if self.scope_pin is not None else -1
        self._build_cycle(self._out.fd if self._out is not None else -1,
                          [_bit(self._out, offset) for offset in out_offsets[:len(self.outputs)]],
                          self._in.fd if self._in is not None else -1,
                          [_bit(self._in, offset) for offset in in_offsets],
                          self._estop.fd if self._estop is not None else -1)
        if self._estop is not None:
            # pressed already (its active level, after the edge that would stop): refuse to start
            level = self._estop.get_value(self._estop.offsets[0])
            engaged = (level == Value.ACTIVE) if self.estop_edge == "rising" else (
                level == Value.INACTIVE if self.estop_edge == "falling" else False)
            if engaged:
                self.close()
                raise DeviceError(self.name, "", "estop", f"the E-stop line {self.estop!r} is engaged: release it "
                                  "before starting")

    def _build_cycle(self, out_fd: int, out_bits: list[int], in_fd: int, in_bits: list[int], estop_fd: int) -> None:
        """What every cycle uses, built once: the line requests' fds, each line's bit in its request's
        values, the buffers; the C cycle where it was built (any fds will do: the tests build it on
        stand-ins to compare it with the reference)."""
        self._out_fd, self._in_fd, self._estop_fd = out_fd, in_fd, estop_fd
        self._out_bits, self._in_bits = out_bits, in_bits
        self._out_mask = sum(1 << bit for bit in out_bits)
        self._in_mask = sum(1 << bit for bit in in_bits)
        self._values = bytearray(GPIO_V2_LINE_VALUES.size)
        self._in_values = bytearray(GPIO_V2_LINE_VALUES.size)
        GPIO_V2_LINE_VALUES.pack_into(self._in_values, 0, 0, self._in_mask)
        self._events = bytearray(GPIO_V2_LINE_EVENT.size * 16)
        self._poller = None
        if estop_fd >= 0:
            self._poller = select.poll()
            self._poller.register(estop_fd, select.POLLIN)
        compiled = devio()  # the same cycle in C (io/_devio.c), where it was built
        if compiled is not None:
            self._lines = compiled.GpioLines(out_fd, GPIO_V2_LINE_SET_VALUES_IOCTL, out_bits, in_fd,
                                             GPIO_V2_LINE_GET_VALUES_IOCTL, in_bits, estop_fd)

    def _request(self, chip: Any, lines: list[Any], key: str, consumer: str, settings: Any) -> tuple[Any, list[int]]:
        """One kernel line request for ``lines`` (None without lines) and their chip offsets."""
        if not lines:
            return None, []
        offsets = [self._offset(chip, key, line) for line in lines]
        config = {offset: settings(str(line) in self.active_low) for offset, line in zip(offsets, lines, strict=True)}
        try:
            request = chip.request_lines(config, consumer=consumer)
        except OSError as error:
            busy = " (busy: another program holds a line; gpioinfo shows which)" if error.errno == 16 else ""
            raise DeviceError(self.name, "", key, f"cannot request lines {lines!r} of {self.chip}: "
                              f"{error.strerror or error}{busy}") from None
        self._requests.append(request)
        return request, offsets

    def write(self, u: FloatVector) -> None:
        """Output i active when u[i] >= 0.5 (a NaN never is: the guard faults on it before), one ioctl."""
        if self._lines is not None:
            try:
                self._lines.write(u)
                return
            except TypeError:  # not a float64 vector (a list): the Python way below
                pass
        if self._out_fd < 0 or not self._out_bits:
            return
        bits, u = 0, self._u.of(u)
        for index, bit in enumerate(self._out_bits):
            if u[index] >= 0.5:
                bits |= 1 << bit
        GPIO_V2_LINE_VALUES.pack_into(self._values, 0, bits, self._out_mask)
        rt.ioctl(self._out_fd, GPIO_V2_LINE_SET_VALUES_IOCTL, self._values, "GPIO_V2_LINE_SET_VALUES_IOCTL")

    def read(self, y: FloatVector) -> None:
        """Stop on a pending E-stop edge; else input i into y[i] as 1.0 (active) or 0.0, one ioctl."""
        if self._lines is not None:
            try:
                if self._lines.read(y):  # an E-stop edge is waiting
                    self._stop_on_edge()
                return
            except TypeError:  # not a float64 vector: the Python way below
                pass
        if self._poller is not None and self._poller.poll(0):
            self._stop_on_edge()
        if self._in_fd < 0:
            return
        values = self._in_values
        rt.ioctl(self._in_fd, GPIO_V2_LINE_GET_VALUES_IOCTL, values, "GPIO_V2_LINE_GET_VALUES_IOCTL")
        bits, y = GPIO_V2_LINE_VALUES.unpack_from(values, 0)[0], self._y.of(y)
        for index, bit in enumerate(self._in_bits):
            y[index] = 1.0 if bits >> bit & 1 else 0.0
        # the kernel wrote the bits; the mask it read must stay for the next call
        GPIO_V2_LINE_VALUES.pack_into(values, 0, 0, self._in_mask)

    def _stop_on_edge(self) -> None:
        """Read the E-stop's first queued edge (its kernel timestamp) and stop the app with it."""
        size = os.readv(self._estop_fd, [self._events])
        timestamp_ns, event_id, _offset, _seqno, _line_seqno = GPIO_V2_LINE_EVENT.unpack_from(self._events, 0)
        assert size >= GPIO_V2_LINE_EVENT.size
        edge = "rising" if event_id == GPIO_V2_LINE_EVENT_RISING_EDGE else "falling"
        raise EmergencyStop(self.name, str(self.estop), edge, timestamp_ns)

    def write_safe_for_dead_task(self, u: FloatVector) -> str:
        """From the supervisor: request the output lines again (the kernel freed them with the dead
        process) driven at their safe levels from the request on, and hold them until the run ends
        (``close``)."""
        from gpiod import LineSettings
        from gpiod.line import Direction, Value

        if not self.outputs:
            return ""
        chip = self._open_chip()
        try:
            levels = [Value.ACTIVE if u[index] >= 0.5 else Value.INACTIVE for index in range(len(self.outputs))]
            config = {self._offset(chip, "outputs", line): LineSettings(
                direction=Direction.OUTPUT, output_value=level, active_low=str(line) in self.active_low)
                for line, level in zip(self.outputs, levels, strict=True)}
            self._requests.append(chip.request_lines(config, consumer=f"rtloop:{self.name}:safe"[:31]))
        finally:
            chip.close()
        shown = ", ".join(f"{line}={int(level == Value.ACTIVE)}"
                          for line, level in zip(self.outputs, levels, strict=True))
        return f"holds its output lines at their safe levels ({shown}) until the run ends"

    # --- the scope pin, driven by the task's devices (io/host.py ScopePin) -----------------------
    def scope_output(self) -> tuple[int, int, int, int] | None:
        """The scope pin (io/host.py ``ScopePin``): (line request fd, its
        SET_VALUES ioctl number, the pin's bit in the request, mode 1 toggle / 2 high during step);
        None without a scope pin."""
        if self.scope_pin is None or self._out is None:
            return None
        return self._out_fd, GPIO_V2_LINE_SET_VALUES_IOCTL, self._scope_bit, SCOPE_MODES.index(self.scope_mode) + 1

    def close(self) -> None:
        if self._lines is not None:
            self._lines.release()  # before the requests close the fds it uses (and their numbers are reused)
            self._lines = None
        for request in self._requests:
            try:
                request.release()
            except Exception:
                pass  # already released; the fd closes with the process anyway
        self._requests = []
        self._out = self._in = self._estop = None
        self._out_fd = self._in_fd = self._estop_fd = -1


def _bit(request: Any, offset: int) -> int:
    """Where ``offset`` sits in the request's value bitmap (the kernel's order of the requested lines)."""
    return list(request.offsets).index(offset)
