"""The servos of a bus as an app declares them, and their units: radians at the task, ticks on the wire.

Each servo: ``{ name, id, model, zero_ticks, direction, range_rad }`` — LeRobot's calibration idea:
the raw position that is 0 rad (``zero_ticks``, default 2048: the middle of the turn), the sense
(``direction`` 1 or -1: which way is positive at the joint), and the joint's range in radians,
which must lie within the servo's one turn (0..4095 ticks) and, at configure, within the
position limits stored in the servo. Conversions are vectorised over the servos, on arrays made once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from rtloop.errors import DeviceError
from rtloop.io.servos.tables import RAD_PER_TICK, TICKS_PER_TURN, Family, ServoModel

SERVO_KEYS = ("name", "id", "model", "zero_ticks", "direction", "range_rad")
COMMAND_UNITS = {"position": "position_rad", "velocity": "velocity_rad_s", "current": "current_A", "pwm": "pwm"}
MAX_SERVO_ID = 252  # 253..255: the header byte, broadcast (254) and reserved


@dataclass(frozen=True, slots=True)
class ServoSpec:
    name: str
    servo_id: int
    model: ServoModel
    zero_ticks: int
    direction: int
    range_rad: tuple[float, float]

    def ticks(self, angle_rad: float) -> float:
        return self.zero_ticks + self.direction * angle_rad / RAD_PER_TICK

    def range_ticks(self) -> tuple[int, int]:
        ends = sorted(self.ticks(angle) for angle in self.range_rad)
        return math.ceil(ends[0] - 1e-9), math.floor(ends[1] + 1e-9)


def parse_servos(device: str, family: Family, command: str, servos: list[Any]) -> list[ServoSpec]:
    """The ``servos`` setting, checked: each mistake one :class:`DeviceError` naming ``servos[i].key``."""
    if not servos:
        raise DeviceError(device, "", "servos", "no servo; expected [{ name = \"pan\", id = 1, model = ..., "
                          "range_rad = [-1.5, 1.5] }, ...]")
    specs: list[ServoSpec] = []
    for index, table in enumerate(servos):
        where = f"servos[{index}]"
        if not isinstance(table, dict):
            raise DeviceError(device, "", where, "expected a table { name, id, model, range_rad, ... }")
        unknown = sorted(set(table) - set(SERVO_KEYS))
        if unknown:
            raise DeviceError(device, "", f"{where}.{unknown[0]}", f"unknown key; expected one of {list(SERVO_KEYS)}")
        for key in ("name", "id", "model", "range_rad"):
            if key not in table:
                raise DeviceError(device, "", f"{where}.{key}", "missing")
        name, servo_id, model_name = table["name"], table["id"], table["model"]
        if not isinstance(name, str) or not name.isidentifier():
            raise DeviceError(device, "", f"{where}.name", f"expected a name (letters, digits, _), got {name!r}")
        if isinstance(servo_id, bool) or not isinstance(servo_id, int) or not 0 <= servo_id <= MAX_SERVO_ID:
            raise DeviceError(device, "", f"{where}.id", f"expected an integer 0..{MAX_SERVO_ID}, got {servo_id!r}")
        model = family.model_named(model_name) if isinstance(model_name, str) else None
        if model is None:
            raise DeviceError(device, "", f"{where}.model", f"{model_name!r} is not a {family.protocol} model rtloop "
                              f"knows; known: {', '.join(family.models)}")
        zero = table.get("zero_ticks", TICKS_PER_TURN // 2)
        if isinstance(zero, bool) or not isinstance(zero, int) or not 0 <= zero < TICKS_PER_TURN:
            raise DeviceError(device, "", f"{where}.zero_ticks", f"expected an integer 0..4095, got {zero!r}")
        direction = table.get("direction", 1)
        if direction not in (1, -1) or isinstance(direction, bool):
            raise DeviceError(device, "", f"{where}.direction", f"expected 1 or -1, got {direction!r}")
        bounds = table["range_rad"]
        if not isinstance(bounds, list) or len(bounds) != 2 or not all(
                isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in bounds) \
                or not bounds[0] < bounds[1]:
            raise DeviceError(device, "", f"{where}.range_rad",
                              f"expected [low, high] in rad, low < high, got {bounds!r}")
        spec = ServoSpec(name, servo_id, model, zero, direction, (float(bounds[0]), float(bounds[1])))
        # a range of ±1e308 rad is ±inf ticks, which no int holds; a finite one is said in ticks below
        if not all(math.isfinite(spec.ticks(angle)) for angle in spec.range_rad):
            raise DeviceError(device, "", f"{where}.range_rad", f"[{bounds[0]:g}, {bounds[1]:g}] rad reaches past "
                              f"one turn around zero_ticks {zero}: outside the servo's 0..4095")
        low, high = spec.range_ticks()
        if low < 0 or high >= TICKS_PER_TURN:
            raise DeviceError(device, "", f"{where}.range_rad", f"[{bounds[0]:g}, {bounds[1]:g}] rad is ticks "
                              f"{low}..{high} around zero_ticks {zero}: outside the servo's 0..4095 (one turn)")
        if command == "current" and not model.current_A_per_unit:
            raise DeviceError(device, "", f"{where}.model", f"a {model.name} measures load, not current: "
                              "command = \"current\" needs a model with current sensing")
        if command == "pwm" and not model.pwm_limit_units:
            raise DeviceError(device, "", "command", f"a {model.name} takes no PWM command")
        for other_index, other in enumerate(specs):
            for key, mine, theirs in (("id", servo_id, other.servo_id), ("name", name, other.name)):
                if mine == theirs:
                    raise DeviceError(device, "", f"{where}.{key}", f"{mine!r} is also servos[{other_index}]'s")
        specs.append(spec)
    return specs


class Units:
    """Per-servo scales between the task's SI values and the wire's integers (arrays made once)."""

    def __init__(self, family: Family, command: str, specs: list[ServoSpec]) -> None:
        self.specs = specs
        n = len(specs)
        direction = np.array([spec.direction for spec in specs], dtype=np.float64)
        models = [spec.model for spec in specs]
        self.zero = np.array([spec.zero_ticks for spec in specs], dtype=np.float64)
        self.position_rad = direction * RAD_PER_TICK
        self.velocity_rad_s = direction * np.array([m.velocity_rad_s_per_unit for m in models])
        signed_current = family.fields["present_current"].encoding != "u"
        self.current = (direction if signed_current else np.ones(n)) * np.array(
            [m.current_A_per_unit or 0.001 for m in models])  # load: 0.1 % units as a fraction
        if command == "position":
            ticks = [spec.range_ticks() for spec in specs]
            self.command_scale = direction / RAD_PER_TICK
            self.command_offset = self.zero.copy()
            self.command_low = np.array([low for low, _ in ticks], dtype=np.float64)
            self.command_high = np.array([high for _, high in ticks], dtype=np.float64)
        else:
            unit, limit = {
                "velocity": ([m.velocity_rad_s_per_unit for m in models], [m.velocity_limit_units for m in models]),
                "current": ([m.current_A_per_unit for m in models], [m.current_limit_units for m in models]),
                "pwm": ([1.0 / m.pwm_limit_units if m.pwm_limit_units else 1.0 for m in models],
                        [m.pwm_limit_units for m in models]),
            }[command]
            self.command_scale = direction / np.array(unit)
            self.command_offset = np.zeros(n)
            self.command_high = np.array(limit, dtype=np.float64)
            self.command_low = -self.command_high
        self.command_unit = COMMAND_UNITS[command]
        self.command = command

    def command_bounds_si(self, index: int) -> tuple[float, float]:
        """The command's [min, max] in SI for servo ``index`` (its range, or its model's limits)."""
        if self.command == "position":
            return self.specs[index].range_rad
        limit = self.command_high[index] / abs(self.command_scale[index])
        return -float(limit), float(limit)

    def reading_names(self) -> list[str]:
        """Every servo's position, then every velocity, current (or load), error: ``y[0:n]`` are the positions."""
        specs = self.specs
        return [*(f"{s.name}_position_rad" for s in specs), *(f"{s.name}_velocity_rad_s" for s in specs),
                *(f"{s.name}_{'current_A' if s.model.current_A_per_unit else 'load'}" for s in specs),
                *(f"{s.name}_error" for s in specs)]

    def command_names(self) -> list[str]:
        return [f"{spec.name}_{self.command_unit}" for spec in self.specs]
