"""Servos that speak the real protocol: a control table, a motor behind it, faults on demand.

:class:`BusModel` takes instruction packets as bytes and answers status packets as bytes, as
the servos on a bus do: PING, READ, WRITE, SYNC_WRITE, SYNC_READ of Dynamixel 2.0 or Feetech
(:mod:`.protocol`), each servo with its own control table (:mod:`.tables`). The emulator
serves it on a pseudo-terminal (``rtloop emulate``); the device's twin runs it in process.

**Time moves at each SYNC_READ**: one sync read is one period of the app (``period_s``). A run
asks once per cycle, so the servos move in lock-step with the controller (a hardware
*simulator*, not a clock): a run over a pty equals its simulation with the twin bit for bit.

**The motor**: the output shaft with the gearbox's inertia and friction, driven by the servo's
own loop (position: PD; velocity: P; current: torque ∝ current; PWM: a DC motor's line from
stall torque to no-load speed), its torque bounded by that same line. Torque off: it coasts.

**Faults**: a servo that goes silent after N sync reads (it answers nothing from then on), and
a hardware error after N sync reads (the error bits set, torque off by itself, as both families
do; Dynamixel sets the alert bit of every status it sends from then on).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from rtloop.io.servos.protocol import (
    BAD,
    BROADCAST_ID,
    DXL_ALERT,
    NEED_MORE,
    PING,
    PROTOCOLS,
    READ,
    SYNC_READ,
    SYNC_WRITE,
    WRITE,
    Dynamixel2,
    Scan,
    destuff,
)
from rtloop.io.servos.tables import FAMILIES, RAD_PER_TICK, Family, Field, ServoModel

SUBSTEP_S = 0.00025
"""The motor is integrated in steps of at most 0.25 ms within a period."""
INERTIA_KGM2 = 0.004
"""Output shaft, gearbox reflected (a small servo with a light link)."""
POSITION_STIFFNESS_RAD = 0.15
"""The servo's position loop gives its stall torque at this error."""
TABLE_BYTES = 256
EEPROM_END = 64
"""Dynamixel X: addresses below are EEPROM, written only with torque off."""


@dataclass(frozen=True, slots=True)
class Faults:
    silent_after_reads: int | None = None
    """The servo answers this many sync reads, then nothing more."""
    hardware_error_after_reads: int | None = None
    """After this many sync reads: a hardware error, torque off."""
    hardware_error_bits: int = 0x20
    """The error bits then (0x20: overload, in both families)."""


def encode(field: Field, value: int) -> bytes:
    if field.encoding == "m15":
        value = min(abs(value), 0x7FFF) | (0x8000 if value < 0 else 0)
    elif field.encoding == "u":
        value = max(0, min(value, (1 << 8 * field.width) - 1))
    else:
        limit = 1 << (8 * field.width - 1)
        value = max(-limit, min(value, limit - 1))
    return value.to_bytes(field.width, "little", signed=field.encoding == "s")


def decode(field: Field, data: bytes | bytearray) -> int:
    raw = int.from_bytes(data, "little", signed=field.encoding == "s")
    if field.encoding == "m15":
        return -(raw & 0x7FFF) if raw & 0x8000 else raw
    return raw


class ServoState:
    """One servo: its control table and its motor."""

    def __init__(self, family: Family, servo_id: int, model: ServoModel, position_ticks: int = 2048,
                 faults: Faults = Faults(), baud_rate: int = 1_000_000) -> None:
        self.family, self.servo_id, self.model, self.faults = family, servo_id, model, faults
        self.table = bytearray(TABLE_BYTES)
        baud_value = next((value for value, rate in family.baud_rates.items() if rate == baud_rate), 0)
        for name, value in (("model_number", model.number), ("id", servo_id), ("baud_rate", baud_value),
                            ("operating_mode", family.modes["position"]), ("min_position", 0),
                            ("max_position", 4095), ("goal_position", position_ticks)):
            self.set(name, value)
        if "current_limit" in family.fields:
            self.set("current_limit", model.current_limit_units)
            self.set("pwm_limit", model.pwm_limit_units)
            self.set("velocity_limit", model.velocity_limit_units)
        self.angle_rad = position_ticks * RAD_PER_TICK
        self.velocity_rad_s = 0.0
        self.torque_Nm = 0.0
        self.reads = 0
        self.silent = False
        self.error_bits = 0
        self.publish()

    # --- the control table --------------------------------------------------------------------
    def get(self, name: str) -> int:
        field = self.family.fields[name]
        return decode(field, self.table[field.address:field.address + field.width])

    def set(self, name: str, value: int) -> None:
        field = self.family.fields[name]
        self.table[field.address:field.address + field.width] = encode(field, value)

    @property
    def torque_on(self) -> bool:
        return bool(self.table[self.family.fields["torque_enable"].address])

    # --- the motor ----------------------------------------------------------------------------
    def advance(self, period_s: float) -> None:
        """One period: the servo's loop drives the motor, then the present values are updated."""
        steps = max(1, math.ceil(period_s / SUBSTEP_S - 1e-9))
        dt = period_s / steps
        model = self.model
        stall, free_speed = model.stall_torque_Nm, model.no_load_speed_rad_s
        friction = 0.02 * stall / free_speed
        mode = self.get("operating_mode")
        modes = self.family.modes
        torque_on = self.torque_on
        goal = 0.0
        if torque_on:
            name = next((kind for kind, value in modes.items() if value == mode), "position")
            goal = float(self.get(self.family.goals[name]))
        for _ in range(steps):
            torque = 0.0
            if torque_on:
                if mode == modes["position"]:
                    error = goal * RAD_PER_TICK - self.angle_rad
                    stiffness = stall / POSITION_STIFFNESS_RAD
                    torque = stiffness * error - 2.0 * math.sqrt(stiffness * INERTIA_KGM2) * self.velocity_rad_s
                elif mode == modes["velocity"]:
                    torque = stall * 4.0 * (goal * model.velocity_rad_s_per_unit - self.velocity_rad_s) / free_speed
                elif mode == modes.get("current"):
                    torque = stall * goal / max(1, model.current_limit_units)
                elif mode == modes.get("pwm"):
                    torque = stall * (goal / max(1, model.pwm_limit_units) - self.velocity_rad_s / free_speed)
                # the motor's line: no more than stall torque at rest, none at no-load speed
                torque = min(torque, stall * (1.0 - self.velocity_rad_s / free_speed))
                torque = max(torque, -stall * (1.0 + self.velocity_rad_s / free_speed))
            self.torque_Nm = torque
            self.velocity_rad_s += dt * (torque - friction * self.velocity_rad_s) / INERTIA_KGM2
            self.angle_rad += dt * self.velocity_rad_s
        self.publish()

    def publish(self) -> None:
        model = self.model
        self.set("present_position", round(self.angle_rad / RAD_PER_TICK))
        self.set("present_velocity", round(self.velocity_rad_s / model.velocity_rad_s_per_unit))
        if model.current_A_per_unit:
            current_A = self.torque_Nm / model.stall_torque_Nm * model.current_limit_units * model.current_A_per_unit
            units = round(current_A / model.current_A_per_unit)
        else:  # a model that measures load (0.1 % of stall torque)
            units = round(1000 * self.torque_Nm / model.stall_torque_Nm)
        self.set("present_current", abs(units) if self.family.fields["present_current"].encoding == "u" else units)

    # --- faults -------------------------------------------------------------------------------
    def sync_read(self) -> bool:
        """Counted at each sync read; False when the servo is silent from now on."""
        self.reads += 1
        faults = self.faults
        if faults.silent_after_reads is not None and self.reads > faults.silent_after_reads:
            self.silent = True
        if faults.hardware_error_after_reads is not None and self.reads > faults.hardware_error_after_reads \
                and not self.error_bits:
            self.error_bits = faults.hardware_error_bits
            if "hardware_error" in self.family.fields:
                self.set("hardware_error", self.error_bits)
            return True
        return not self.silent

    def status_error(self) -> int:
        if self.family.protocol == "dynamixel":
            return DXL_ALERT if self.error_bits else 0
        return self.error_bits


class BusModel:
    """The servos of one bus: instruction bytes in, status bytes out (see the module)."""

    def __init__(self, protocol: str, servos: list[ServoState], period_s: float,
                 log: Callable[[str], None] | None = None) -> None:
        self.protocol = PROTOCOLS[protocol]
        self.family = FAMILIES[protocol]
        self.servos = {servo.servo_id: servo for servo in servos}
        self.period_s = period_s
        self.log = log or (lambda _text: None)
        self.incoming = bytearray()
        self.scan = Scan()
        self.sync_reads = 0

    def receive(self, data: bytes | bytearray | memoryview) -> bytes:
        """Take instruction bytes; return the status packets the servos send back (maybe none)."""
        self.incoming += data
        answers = bytearray()
        start = 0
        incoming, scan = self.incoming, self.scan
        while start < len(incoming):
            size = self.protocol.scan(incoming, start, len(incoming), scan, False)
            if size == NEED_MORE:
                break
            if size == BAD:
                start += 1  # noise, or a packet cut short: look for the next header
                continue
            params = bytes(incoming[scan.first:scan.end])
            if isinstance(self.protocol, Dynamixel2):
                params = destuff(params)
            answers += self.handle(scan.servo_id, scan.instruction, params)
            start += size
        del incoming[:start]
        return bytes(answers)

    def handle(self, servo_id: int, instruction: int, params: bytes) -> bytes:
        width = self.protocol.address_bytes
        if instruction == SYNC_READ:
            return self._sync_read(params, width)
        if instruction == SYNC_WRITE:
            address, length = self._range(params, width)
            body = params[2 * width:]
            for at in range(0, len(body) - length + 1, 1 + length):
                servo = self.servos.get(body[at])
                if servo is not None and not servo.silent:
                    self._write(servo, address, body[at + 1:at + 1 + length])
            return b""
        targets = list(self.servos.values()) if servo_id == BROADCAST_ID else \
            [self.servos[servo_id]] if servo_id in self.servos else []
        answers = bytearray()
        for servo in targets:
            if servo.silent:
                continue
            if instruction == PING:
                data = servo.table[0:2] + servo.table[6:7] if self.family.protocol == "dynamixel" else b""
                answers += self.protocol.status(servo.servo_id, servo.status_error(), bytes(data))
            elif instruction == READ:
                address, length = self._range(params, width)
                answers += self.protocol.status(servo.servo_id, servo.status_error(),
                                                bytes(servo.table[address:address + length]))
            elif instruction == WRITE:
                address = int.from_bytes(params[:width], "little")
                error = self._write(servo, address, params[width:])
                if servo_id != BROADCAST_ID:
                    answers += self.protocol.status(servo.servo_id, error or servo.status_error(), b"")
        return bytes(answers)

    @staticmethod
    def _range(params: bytes, width: int) -> tuple[int, int]:
        return int.from_bytes(params[:width], "little"), int.from_bytes(params[width:2 * width], "little")

    def _write(self, servo: ServoState, address: int, data: bytes) -> int:
        """Write the control table as the servo would; the status error byte (0: done)."""
        if address + len(data) > TABLE_BYTES:
            return 4 if self.family.protocol == "dynamixel" else 0  # data range error
        torque = self.family.fields["torque_enable"].address
        if self.family.protocol == "dynamixel" and address < EEPROM_END and servo.torque_on:
            return 7  # access error: EEPROM is locked while torque is on
        was_on = servo.torque_on
        servo.table[address:address + len(data)] = data
        if servo.error_bits and servo.table[torque]:
            servo.table[torque] = 0  # a servo in error keeps its torque off until rebooted
        if servo.torque_on != was_on:
            self.log(f"servo {servo.servo_id}: torque {'on' if servo.torque_on else 'off'} (host)")
        return 0

    def _sync_read(self, params: bytes, width: int) -> bytes:
        self.sync_reads += 1
        for servo in self.servos.values():
            servo.advance(self.period_s)
        address, length = self._range(params, width)
        answers = bytearray()
        for servo_id in params[2 * width:]:
            asked = self.servos.get(servo_id)
            if asked is None:
                continue
            servo = asked
            had_error = servo.error_bits
            answering = servo.sync_read()
            if servo.error_bits and not had_error:
                torque = self.family.fields["torque_enable"].address
                was_on = servo.table[torque]
                servo.table[torque] = 0
                self.log(f"servo {servo_id}: hardware error 0x{servo.error_bits:02x} "
                         f"({self.family.error_words(servo.error_bits)}) at sync read {self.sync_reads}"
                         + (": torque off" if was_on else ""))
            if not answering:
                if servo.silent and servo.reads == (servo.faults.silent_after_reads or 0) + 1:
                    self.log(f"servo {servo_id}: silent from sync read {self.sync_reads} on")
                continue
            answers += self.protocol.status(servo_id, servo.status_error(),
                                            bytes(servo.table[address:address + length]))
        return bytes(answers)


def build_bus(protocol: str, servo_ids: list[int], models: list[str], period_s: float,
              positions_ticks: list[int] | None = None, faults: dict[int, Faults] | None = None,
              log: Callable[[str], None] | None = None, baud_rate: int = 1_000_000) -> BusModel:
    """A bus of servos ``servo_ids`` of ``models`` (one each, or one for all), at rest at ``positions_ticks``."""
    family = FAMILIES[protocol]
    if len(models) == 1:
        models = models * len(servo_ids)
    servos = []
    for index, servo_id in enumerate(servo_ids):
        model = family.model_named(models[index])
        if model is None:
            raise ValueError(f"unknown {protocol} model {models[index]!r}; known: {', '.join(family.models)}")
        ticks = positions_ticks[index] if positions_ticks else 2048
        servos.append(ServoState(family, servo_id, model, ticks, (faults or {}).get(servo_id, Faults()), baud_rate))
    return BusModel(protocol, servos, period_s, log)
