"""Smart servo buses as devices: ``kind = "dynamixel"`` (Protocol 2.0, X series) and ``kind = "feetech"`` (STS).

Per cycle, for every servo on the bus at once (:mod:`.protocol`):

- ``write(u)``: one SYNC_WRITE of the goals (``command``: position, velocity, current or PWM), in SI
  at the task (rad, rad/s, A, duty −1..1), converted, rounded and clamped to each servo's range;
- ``read(y)``: one SYNC_READ of present position, velocity and current, with each servo's
  status error byte: every servo's ``NAME_position_rad`` (``y[0:n]``), then every
  ``NAME_velocity_rad_s``, ``NAME_current_A`` (``NAME_load``, a fraction, for a model that
  measures load) and ``NAME_error`` (its hardware error bits, 0 when well).

The packets' CRC-16 (Dynamixel) or checksum (Feetech), and the sync read's scan of the answers, run in C
where ``io/_devio.c`` was built (``io/devio_c/servo.c``; ``io/compiled.py``), else as the Python references
of :mod:`.protocol`.

A servo whose answer does not come whole and good within ``timeout_ms`` keeps its last readings
and is counted stale (``on_missing = "stale"``, at most ``max_stale_in_a_row`` in a row), or is a
fault (``"fault"``). A hardware error (Dynamixel: the alert bit, then its error status read once;
Feetech: the error bits) is a fault (``on_hardware_error = "fault"``) or a reading the task handles
(``"report"``).

Set-up goes through plain instructions with their answers, outside the loop: at ``configure`` each
servo is pinged and its model number, baud rate, position limits and operating mode checked (a
servo not on the bus while others answer, another model, a range outside its limits: bad input,
exit 2; no servo answering: not ready, exit 3); at ``activate`` the goals are set to where the
servos are and torque is enabled. The **safe state** is a transition: ``safe_state =
"torque_off"`` writes torque off to each servo and waits for each to confirm; ``"hold"`` keeps
torque on and sets the goal to where each servo is (an arm that would fall).
"""

from __future__ import annotations

import os
from typing import Any, ClassVar

import numpy as np

from rtloop.errors import DeviceError, DeviceFault, DeviceMismatch, DeviceNotReady
from rtloop.io.device import HOUR_MS, Claim, CommandLimit, Device, FloatVector, Setting, positive
from rtloop.io.servos.calibration import ServoSpec, Units, parse_servos
from rtloop.io.servos.line import PortLine
from rtloop.io.servos.protocol import (
    DXL_ALERT,
    DXL_ERRORS,
    PING,
    PROTOCOLS,
    READ,
    WRITE,
    Line,
    SyncRead,
    SyncWrite,
    for_the_cycle,
    request,
)
from rtloop.io.servos.tables import FAMILIES, Family
from rtloop.runnable import Runnable

SETUP_TIMEOUT_NS = 200_000_000
"""A set-up instruction's answer (not in the loop) may take this long, at least."""
SETUP_TRIES = 3
ON_MISSING = ("fault", "stale")
ON_HARDWARE_ERROR = ("fault", "report")
SAFE_STATES = ("torque_off", "hold")


def _one_of(choices: tuple[str, ...]) -> Any:
    return lambda value: None if value in choices else f"expected one of {', '.join(choices)}, got {value!r}"


class ServoBusDevice(Device):
    """The servos on one serial line (see the module). Subclasses name the protocol."""

    protocol_name: ClassVar[str] = ""
    settings: ClassVar[dict[str, Setting]] = {
        "port": Setting(str, doc="the serial device, e.g. /dev/ttyUSB0 (an FTDI adapter: latency_timer 1 ms)",
                        is_path=True),
        "baudrate": Setting(int, 1_000_000, "bits per second, as the servos are set",
                            check=positive, at_most=100_000_000),
        "servos": Setting(list, doc="[{ name, id, model, zero_ticks, direction, range_rad }, ...]"),
        "command": Setting(str, "position", "what the task commands: position (rad), velocity (rad/s), "
                           "current (A), pwm (duty -1..1)"),
        "timeout_ms": Setting(float, 5.0, "how long a sync read waits for every servo's answer, in ms",
                              check=positive, at_most=HOUR_MS),
        "on_missing": Setting(str, "fault", "a servo not answering within timeout_ms: \"fault\" or \"stale\" "
                              "(keep its last readings, count)", check=_one_of(ON_MISSING)),
        "max_stale_in_a_row": Setting(int, 10, "with on_missing = \"stale\": this many reads in a row without a "
                                      "servo's answer are a fault", check=lambda v: None if v >= 1 else "must be ≥ 1"),
        "on_hardware_error": Setting(str, "fault", "a servo reporting a hardware error: \"fault\" (stop, safe "
                                     "state) or \"report\" (its NAME_error reading says it)",
                                     check=_one_of(ON_HARDWARE_ERROR)),
        "safe_state": Setting(str, "torque_off", "on every way a run ends: \"torque_off\", or \"hold\" (torque "
                              "stays on, the goal where the servo is)", check=_one_of(SAFE_STATES)),
    }

    def __init__(self, name: str, **settings: Any) -> None:
        super().__init__(name, **settings)
        defaults = {key: setting.default for key, setting in self.settings.items() if not setting.required}
        self.config = settings = {**defaults, **settings}
        family = self.family
        command = settings["command"]
        if command not in family.goals:
            raise DeviceError(name, "", "command", f"{command!r}; a {self.kind} bus takes {', '.join(family.goals)}")
        if settings["safe_state"] == "hold" and command not in ("position", "velocity"):
            raise DeviceError(name, "", "safe_state", f"\"hold\" needs command = \"position\" or \"velocity\" "
                              f"(a {command} of 0 holds nothing)")
        self.specs: list[ServoSpec] = parse_servos(name, family, command, settings["servos"])
        self.units = Units(family, command, self.specs)
        self.input_names = tuple(self.units.command_names())
        self.output_names = tuple(self.units.reading_names())
        self.n_inputs, self.n_outputs = len(self.input_names), len(self.output_names)
        self.timeout_ns = round(settings["timeout_ms"] * 1e6)
        self.stale_by_servo = [0] * len(self.specs)
        self._port: Any = None
        self.line: Line | None = None

    @property
    def family(self) -> Family:
        return FAMILIES[self.protocol_name]

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_port": None, "line": None}  # an open port never travels

    # --- description ------------------------------------------------------------------------------
    def default_limits(self) -> dict[str, CommandLimit]:
        limits = {}
        for index, command in enumerate(self.command_names()):
            low, high = self.units.command_bounds_si(index)
            limits[command] = CommandLimit(low, high, min(max(0.0, low), high))
        return limits

    def claims(self) -> tuple[Claim, ...]:
        port = os.path.realpath(self.config["port"])
        return (Claim(("serial line", port), "port", f"serial line {port} is also"),)

    def check(self) -> None:
        from rtloop.io.serial import SerialDevice

        SerialDevice.check(self)  # type: ignore[arg-type]  # the same port checks (exists, a tty, ours, may open)

    def default_twin(self) -> Runnable:
        from rtloop.io.servos.twin import ServoBusTwin

        return ServoBusTwin(type(self), self.name, self.config, self.n_inputs, self.n_outputs)

    # --- set-up -----------------------------------------------------------------------------------
    def configure(self) -> None:
        import serial

        port = self.config["port"]
        try:
            self._port = serial.Serial(port, self.config["baudrate"], timeout=0, write_timeout=0, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as error:
            raise DeviceError(self.name, "", "port", f"cannot open {port}: {error}") from None
        self._port.reset_input_buffer()
        self.attach(PortLine(self._port.fileno()))

    def attach(self, line: Line) -> None:
        """Check the servos on ``line`` and build the per-cycle packets (configure's work past opening)."""
        self.line = line
        family = self.family
        protocol = for_the_cycle(self.protocol_name)  # its CRC/checksum in C where built
        answered = [self._ping(spec) for spec in self.specs]
        if not any(answer is not None for answer in answered):
            raise DeviceNotReady(self.name, "", "port", f"no servo answered on {self.config['port']} at "
                                 f"{self.config['baudrate']} baud (IDs "
                                 f"{', '.join(str(s.servo_id) for s in self.specs)})"
                                 ": is the bus powered and wired (data, ground), and are the servos at that baud rate?")
        for index, (spec, answer) in enumerate(zip(self.specs, answered, strict=True)):
            if answer is None:
                found = ", ".join(str(s.servo_id) for s, a in zip(self.specs, answered, strict=True) if a is not None)
                raise DeviceMismatch(self.name, "", f"servos[{index}].id", f"servo {spec.servo_id} ({spec.name}) is "
                                     f"not on the bus at {self.config['port']}: no answer to a ping (servos {found} "
                                     "answered)")
            self._check_servo(index, spec)
        mode = family.modes[self.config["command"]]
        for spec in self.specs:  # the operating mode is EEPROM: written with torque off only
            if self._read(spec, "operating_mode") != mode:
                problem = self._write(spec, "torque_enable", 0) or self._write(spec, "operating_mode", mode)
                if problem:
                    raise DeviceNotReady(self.name, "", "command", f"servo {spec.servo_id} ({spec.name}) did not "
                                         f"take operating mode {mode} ({self.config['command']}): {problem}")
        ids = [spec.servo_id for spec in self.specs]
        self.goals = SyncWrite(protocol, family.fields[family.goals[self.config["command"]]], ids)
        first, width = family.state_range()
        self.state = SyncRead(protocol, first, width, ids)
        self.positions = self.state.values(family.fields["present_position"])
        self.velocities = self.state.values(family.fields["present_velocity"])
        self.currents = self.state.values(family.fields["present_current"])
        n = len(ids)
        self.raw = np.zeros(n)
        self.readings = np.zeros(self.n_outputs)
        self.reading_position = self.readings[0:n]
        self.reading_velocity = self.readings[n:2 * n]
        self.reading_current = self.readings[2 * n:3 * n]
        self.reading_error = self.readings[3 * n:]
        self.hardware_bits = np.zeros(n)  # Dynamixel: each servo's error status, read once at its alert
        self.stale_in_a_row = np.zeros(n, dtype=np.int64)
        self.missing = np.zeros(n, dtype=bool)
        self.incomplete = False
        self.error_shown = False  # a NAME_error reading is not 0

    def _ping(self, spec: ServoSpec) -> tuple[int, bytes] | None:
        for _ in range(SETUP_TRIES):
            answer = self._request(spec, PING, b"")
            if answer is not None:
                return answer
        return None

    def _request(self, spec: ServoSpec, instruction: int, params: bytes) -> tuple[int, bytes] | None:
        assert self.line is not None
        timeout_ns = max(self.timeout_ns, SETUP_TIMEOUT_NS)
        return request(PROTOCOLS[self.protocol_name], self.line, spec.servo_id, instruction, params, timeout_ns)

    def _read(self, spec: ServoSpec, field_name: str) -> int:
        from rtloop.io.servos.model import decode

        field = self.family.fields[field_name]
        protocol = PROTOCOLS[self.protocol_name]
        for _ in range(SETUP_TRIES):
            answer = self._request(spec, READ, protocol.range_params(field.address, field.width))
            if answer is not None and len(answer[1]) == field.width:
                return decode(field, answer[1])
        raise DeviceNotReady(self.name, "", "port", f"servo {spec.servo_id} ({spec.name}) did not answer reading "
                             f"its {field_name.replace('_', ' ')} on {self.config['port']}")

    def _write(self, spec: ServoSpec, field_name: str, value: int) -> str | None:
        """Write one field and wait for the servo's answer: None when done, else what went wrong."""
        from rtloop.io.servos.model import encode

        field = self.family.fields[field_name]
        protocol = PROTOCOLS[self.protocol_name]
        params = field.address.to_bytes(protocol.address_bytes, "little") + encode(field, value)
        for _ in range(SETUP_TRIES):
            answer = self._request(spec, WRITE, params)
            if answer is not None:
                error = answer[0] & ~DXL_ALERT if self.protocol_name == "dynamixel" else 0
                return f"error {error} ({DXL_ERRORS.get(error, '?')})" if error else None
        return "no answer"

    def _check_servo(self, index: int, spec: ServoSpec) -> None:
        family = self.family
        number = self._read(spec, "model_number")
        if number != spec.model.number:
            found = family.model_numbered(number)
            raise DeviceMismatch(self.name, "", f"servos[{index}].model", f"servo {spec.servo_id} ({spec.name}) is "
                                 f"{'a ' + found.name if found else 'an unknown model'} (model number {number}); "
                                 f"the app says {spec.model.name} ({spec.model.number})")
        rate = family.baud_rates.get(self._read(spec, "baud_rate"))
        if rate != self.config["baudrate"]:
            raise DeviceMismatch(self.name, "", "baudrate", f"servo {spec.servo_id} ({spec.name}) is set to {rate} "
                                 f"baud; the app says {self.config['baudrate']}")
        low, high = self._read(spec, "min_position"), self._read(spec, "max_position")
        want_low, want_high = spec.range_ticks()
        if want_low < low or want_high > high:
            raise DeviceMismatch(self.name, "", f"servos[{index}].range_rad", f"{list(spec.range_rad)} rad is ticks "
                                 f"{want_low}..{want_high}; servo {spec.servo_id} ({spec.name}) allows {low}..{high} "
                                 "(its min/max position limits)")

    # --- at T0 ------------------------------------------------------------------------------------
    def activate(self) -> None:
        """Goals where the servos are (no jump when torque comes on), then torque on, each confirmed."""
        self._hold_here()
        for spec in self.specs:
            problem = self._write(spec, "torque_enable", 1)
            if problem:
                raise DeviceFault(f"device {self.name!r}: servo {spec.servo_id} ({spec.name}) did not enable its "
                                  f"torque: {problem}")

    def _hold_here(self) -> None:
        """Sync write goals that hold the servos where they are (position: their present position; else 0)."""
        if self.config["command"] == "position":
            for index, spec in enumerate(self.specs):
                self.raw[index] = self._read(spec, "present_position")
        else:
            self.raw[:] = 0.0
        self.goals.values.encode(self.raw)
        assert self.line is not None
        self.line.send(self.goals.seal())

    # --- every cycle ------------------------------------------------------------------------------
    def write(self, u: FloatVector) -> None:
        """One sync write of every servo's goal (no answer comes to a sync write)."""
        units = self.units  # (one name a line: no tuple made in the loop)
        raw = self.raw
        np.multiply(u, units.command_scale, out=raw)
        np.add(raw, units.command_offset, out=raw)
        np.rint(raw, out=raw)
        np.minimum(raw, units.command_high, out=raw)
        np.maximum(raw, units.command_low, out=raw)
        self.goals.values.encode(raw)
        try:
            self.line.send(self.goals.seal())  # type: ignore[union-attr]  # configure opened it; no test per cycle
        except OSError as error:
            raise self._line_gone(error) from None

    def read(self, y: FloatVector) -> None:
        """One sync read of every servo's state; a servo that did not answer keeps its last values."""
        state = self.state
        units = self.units
        try:
            if self.incomplete:  # late answers to the last request may still come: not this one's
                self.line.flush_input()  # type: ignore[union-attr]  # configure opened it; no test per cycle
            answered = state.exchange(self.line, self.timeout_ns)  # type: ignore[arg-type]  # opened, as above
        except (OSError, EOFError) as error:
            raise self._line_gone(error) from None
        self.incomplete = answered < len(self.specs)
        if self.incomplete:
            self._missing_answers()
        else:
            self.stale_in_a_row[:] = 0
        # the answers' bytes stay in place for a servo that did not answer: its last values again
        raw = self.raw
        self.positions.decode(raw)
        np.subtract(raw, units.zero, out=raw)
        np.multiply(raw, units.position_rad, out=self.reading_position)
        self.velocities.decode(raw)
        np.multiply(raw, units.velocity_rad_s, out=self.reading_velocity)
        self.currents.decode(raw)
        np.multiply(raw, units.current, out=self.reading_current)
        if np.count_nonzero(state.errors):
            self._status_errors()
        elif self.error_shown:  # every status is clear again (a Feetech voltage dip that passed)
            self.reading_error[:] = 0.0
            self.error_shown = False
        y[:] = self.readings

    def _missing_answers(self) -> None:
        state = self.state
        np.logical_not(state.received, out=self.missing)
        if self.config["on_missing"] == "fault":
            raise DeviceFault(f"device {self.name!r}: {self._missing_phrase()} on {self.config['port']}: "
                              f"{state.problem}; on_missing = \"stale\" keeps its last readings instead")
        self.stale_reads += 1
        np.add(self.stale_in_a_row, self.missing, out=self.stale_in_a_row)
        np.multiply(self.stale_in_a_row, self.missing, out=self.stale_in_a_row)  # an answer resets its count
        for index in np.flatnonzero(self.missing):  # (names the servos: not in a cycle that was whole)
            self.stale_by_servo[index] += 1
        limit = self.config["max_stale_in_a_row"]
        if int(self.stale_in_a_row.max()) >= limit:
            # names the servos that reached the limit, not every one this read missed (those may have missed it once)
            raise DeviceFault(f"device {self.name!r}: {self._missing_phrase(self.stale_in_a_row >= limit)} on "
                              f"{self.config['port']} for {int(self.stale_in_a_row.max())} reads in a row "
                              f"(max_stale_in_a_row = {limit}): {state.problem}")

    def _missing_phrase(self, which: np.ndarray | None = None) -> str:
        gone_ones = self.missing if which is None else which
        names = [f"{spec.servo_id} ({spec.name})" for spec, gone in zip(self.specs, gone_ones, strict=True) if gone]
        return f"servo{'s' if len(names) > 1 else ''} {', '.join(names)} did not answer the sync read"

    def _status_errors(self) -> None:
        """A status error byte that is not 0: a hardware error (fault or reading), or a refused instruction."""
        family = self.family
        for index, spec in enumerate(self.specs):
            error = int(self.state.errors[index])
            if self.protocol_name == "dynamixel":
                if error & ~DXL_ALERT:
                    raise DeviceFault(f"device {self.name!r}: servo {spec.servo_id} ({spec.name}) refused the sync "
                                      f"read: error {error & ~DXL_ALERT} ({DXL_ERRORS.get(error & ~DXL_ALERT, '?')})")
                if error & DXL_ALERT and not self.hardware_bits[index]:
                    self.hardware_bits[index] = self._read(spec, "hardware_error") or DXL_ALERT
                bits = int(self.hardware_bits[index]) if error & DXL_ALERT else 0
            else:
                bits = error
            self.reading_error[index] = bits
            self.error_shown = self.error_shown or bool(bits)
            if bits and self.config["on_hardware_error"] == "fault":
                raise DeviceFault(f"device {self.name!r}: servo {spec.servo_id} ({spec.name}) reports a hardware "
                                  f"error: 0x{bits:02x} ({family.error_words(bits)}); it turns its torque off by "
                                  "itself (on_hardware_error = \"report\" hands it to the task instead)")

    def _line_gone(self, error: BaseException) -> DeviceFault:
        return DeviceFault(f"device {self.name!r}: {self.config['port']} failed under the exchange ({error}: the "
                           "adapter unplugged, or the other end closed)")

    # --- every way out ----------------------------------------------------------------------------
    def write_safe(self, u: FloatVector) -> None:
        """The declared safe state (the values ``u`` are not used: a servo's safe state is a transition)."""
        if self.line is None:
            return
        if self.config["safe_state"] == "hold":
            self._hold_here()
            return
        failed = [f"{spec.servo_id} ({spec.name}): {problem}" for spec in self.specs
                  if (problem := self._write(spec, "torque_enable", 0))]
        if failed:
            raise DeviceFault(f"device {self.name!r}: torque off not confirmed by servo {'; '.join(failed)}")

    def write_safe_for_dead_task(self, u: FloatVector) -> str:
        """Torque off from the supervisor: the dead task's port is free again (its lock went with it)."""
        if self.config["safe_state"] == "hold":
            return "left the servos holding their last goals (safe_state = hold)"
        try:
            self.configure_port_only()
            failed = [spec.servo_id for spec in self.specs if self._write(spec, "torque_enable", 0)]
        finally:
            self.close()
        done = [spec.servo_id for spec in self.specs if spec.servo_id not in failed]
        text = f"turned the torque off on servos {', '.join(map(str, done))} on {self.config['port']}"
        return text + (f" (servos {', '.join(map(str, failed))} did not confirm)" if failed else "")

    def configure_port_only(self) -> None:
        import serial

        self._port = serial.Serial(self.config["port"], self.config["baudrate"], timeout=0, write_timeout=0,
                                   exclusive=True)
        self._port.reset_input_buffer()
        self.line = PortLine(self._port.fileno())

    def close(self) -> None:
        if self._port is not None:
            self._port.close()
            self._port = None
        self.line = None

    # --- stale reads ------------------------------------------------------------------------------
    def may_read_stale(self) -> bool:
        return bool(self.config["on_missing"] == "stale")

    def stale_sources(self) -> dict[str, int]:
        return {f"servo {spec.servo_id} ({spec.name}): no answer": count
                for spec, count in zip(self.specs, self.stale_by_servo, strict=True) if count}


class DynamixelBus(ServoBusDevice):
    """Dynamixel X-series servos, Protocol 2.0."""

    kind = "dynamixel"
    protocol_name = "dynamixel"


class FeetechBus(ServoBusDevice):
    """Feetech STS servos (SO-100 arms), the SCS/STS protocol."""

    kind = "feetech"
    protocol_name = "feetech"
