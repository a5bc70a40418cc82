"""Control tables and servo models: addresses, widths, encodings and units, per protocol.

Facts from the makers' public control tables (ROBOTIS e-Manual for the X series, Feetech's
STS memory table as LeRobot and the Feetech SDK use it). A field is ``(address, bytes,
encoding)``: ``"u"`` unsigned, ``"s"`` two's complement, ``"m15"`` sign and magnitude with the
sign in bit 15 (Feetech's way for signed values). All little-endian.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

TICKS_PER_TURN = 4096
"""Both families' magnetic encoders: 4096 positions a turn (0.088°)."""
RAD_PER_TICK = 2 * math.pi / TICKS_PER_TURN


@dataclass(frozen=True, slots=True)
class Field:
    address: int
    width: int
    encoding: str = "u"


@dataclass(frozen=True, slots=True)
class ServoModel:
    """One model of servo: what rtloop needs to know to check it and to convert its units."""

    name: str
    number: int
    """The model number the servo answers (Dynamixel: in its ping; Feetech: address 3)."""
    current_A_per_unit: float
    """Present/goal current's unit in A (0: the model measures load, not current)."""
    velocity_rad_s_per_unit: float
    current_limit_units: int
    """Largest current command (goal current), in the servo's units."""
    velocity_limit_units: int
    pwm_limit_units: int
    """Goal PWM for 100 % duty (0: no PWM command)."""
    stall_torque_Nm: float
    """For the model (the emulator's motor)."""
    no_load_speed_rad_s: float


@dataclass(frozen=True, slots=True)
class Family:
    """What differs between Dynamixel X and Feetech STS, besides the packets."""

    protocol: str
    fields: dict[str, Field]
    modes: dict[str, int]
    """Command kind → the servo's operating mode value."""
    goals: dict[str, str]
    """Command kind → the field it writes."""
    baud_rates: dict[int, int]
    """Baud rate register value → bits per second."""
    state_fields: tuple[str, ...]
    """Read in one sync read each cycle: one contiguous range."""
    hardware_errors: dict[int, str]
    """Hardware error bits → what they mean."""
    models: dict[str, ServoModel]

    def state_range(self) -> tuple[int, int]:
        """(first address, bytes) of the range the per-cycle sync read covers."""
        first = min(self.fields[name].address for name in self.state_fields)
        last = max(self.fields[name].address + self.fields[name].width for name in self.state_fields)
        return first, last - first

    def model_named(self, name: str) -> ServoModel | None:
        return self.models.get(name.upper())

    def model_numbered(self, number: int) -> ServoModel | None:
        return next((model for model in self.models.values() if model.number == number), None)

    def error_words(self, bits: int) -> str:
        words = [word for bit, word in self.hardware_errors.items() if bits & bit]
        return ", ".join(words) or f"0x{bits:02x}"


RPM = 2 * math.pi / 60

DYNAMIXEL_X = Family(
    protocol="dynamixel",
    fields={
        "model_number": Field(0, 2), "firmware": Field(6, 1), "id": Field(7, 1), "baud_rate": Field(8, 1),
        "return_delay": Field(9, 1), "operating_mode": Field(11, 1), "pwm_limit": Field(36, 2),
        "current_limit": Field(38, 2), "velocity_limit": Field(44, 4), "max_position": Field(48, 4, "s"),
        "min_position": Field(52, 4, "s"), "torque_enable": Field(64, 1), "hardware_error": Field(70, 1),
        "goal_pwm": Field(100, 2, "s"), "goal_current": Field(102, 2, "s"), "goal_velocity": Field(104, 4, "s"),
        "goal_position": Field(116, 4, "s"), "present_current": Field(126, 2, "s"),
        "present_velocity": Field(128, 4, "s"), "present_position": Field(132, 4, "s"),
    },
    modes={"current": 0, "velocity": 1, "position": 3, "pwm": 16},
    goals={"current": "goal_current", "velocity": "goal_velocity", "position": "goal_position", "pwm": "goal_pwm"},
    baud_rates={0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000, 6: 4_000_000,
                7: 4_500_000},
    state_fields=("present_current", "present_velocity", "present_position"),
    hardware_errors={0x01: "input voltage", 0x04: "overheating", 0x08: "motor encoder", 0x10: "electrical shock",
                     0x20: "overload"},
    models={model.name: model for model in (
        ServoModel("XM430-W350", 1020, 0.00269, 0.229 * RPM, 1193, 1023, 885, 4.1, 46 * RPM),
        ServoModel("XM430-W210", 1030, 0.00269, 0.229 * RPM, 1193, 1023, 885, 3.0, 77 * RPM),
        ServoModel("XH430-W350", 1010, 0.00134, 0.229 * RPM, 648, 1023, 885, 3.4, 46 * RPM),
        ServoModel("XM540-W270", 1120, 0.00269, 0.229 * RPM, 2047, 1023, 885, 10.6, 30 * RPM),
        ServoModel("XL330-M288", 1200, 0.001, 0.229 * RPM, 1750, 1023, 885, 0.52, 104 * RPM),
        ServoModel("XL330-M077", 1190, 0.001, 0.229 * RPM, 1750, 1023, 885, 0.215, 383 * RPM),
        ServoModel("XL430-W250", 1060, 0.0, 0.229 * RPM, 0, 1023, 885, 1.5, 57 * RPM),
    )},
)

FEETECH_STS = Family(
    protocol="feetech",
    fields={
        "model_number": Field(3, 2), "id": Field(5, 1), "baud_rate": Field(6, 1), "return_delay": Field(7, 1),
        "min_position": Field(9, 2), "max_position": Field(11, 2), "operating_mode": Field(33, 1),
        "torque_enable": Field(40, 1), "goal_position": Field(42, 2, "m15"), "goal_velocity": Field(46, 2, "m15"),
        "present_position": Field(56, 2, "m15"), "present_velocity": Field(58, 2, "m15"),
        "present_load": Field(60, 2), "status": Field(65, 1), "present_current": Field(69, 2),
    },
    modes={"position": 0, "velocity": 1},
    goals={"position": "goal_position", "velocity": "goal_velocity"},
    baud_rates={0: 1_000_000, 1: 500_000, 2: 250_000, 3: 128_000, 4: 115_200, 5: 57_600, 6: 38_400, 7: 19_200},
    state_fields=("present_position", "present_velocity", "present_current"),
    hardware_errors={0x01: "input voltage", 0x02: "angle sensor", 0x04: "overheat", 0x08: "overcurrent",
                     0x20: "overload"},
    models={model.name: model for model in (
        ServoModel("STS3215", 777, 0.0065, RAD_PER_TICK, 0, 3400, 0, 1.9, 4.7),
        ServoModel("STS3250", 2825, 0.0065, RAD_PER_TICK, 0, 3400, 0, 4.9, 4.4),
    )},
)

FAMILIES = {"dynamixel": DYNAMIXEL_X, "feetech": FEETECH_STS}
