"""The CiA 402 drive profile from the master's side: the state machine done for the user, the
statusword read into readings, the modes, and SI units at the task's side.

Shared by every transport that carries a CiA 402 drive (EtherCAT's CoE process data, CANopen's
PDOs): they move the objects, this module decides what to write and what the objects mean.
Everything here works on Python ints and floats and keeps no per-cycle object: it is called in
the real-time loop.

State machine (CiA 402 / IEC 61800-7-201), as rtloop drives it::

    Not ready to switch on ──(drive)──► Switch on disabled
    Switch on disabled ──shutdown 0x06──► Ready to switch on ──switch on 0x07──► Switched on
    Switched on ──enable operation 0x0F──► Operation enabled
    Operation enabled ──quick stop 0x02──► Quick stop active ──disable voltage 0x00──► Switch on disabled
    Fault ──fault reset (rising edge of bit 7)──► Switch on disabled

On activate rtloop resets a fault, then shuts down, switches on and enables operation, one
transition per exchange (:meth:`JointStateMachine.enabling_controlword`). While the run goes on a
drive that leaves *Operation enabled* is a fault of the run. On every way out the safe
*transition*: quick stop (the drive decelerates on its own quick-stop ramp), then disable
voltage (:meth:`JointStateMachine.stopping_controlword`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

__all__ = [
    "CONTROLWORD",
    "MODES",
    "MODE_NAMES",
    "STATUSWORD",
    "Cia402State",
    "JointScale",
    "JointStateMachine",
    "StatusBits",
    "state_name",
    "state_of",
]

# --- object indices (CiA 402) --------------------------------------------------------------------
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
MODES_OF_OPERATION = 0x6060
MODES_DISPLAY = 0x6061
ERROR_CODE = 0x603F
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TORQUE_ACTUAL = 0x6077
FOLLOWING_ERROR_ACTUAL = 0x60F4
TARGET_POSITION = 0x607A
TARGET_VELOCITY = 0x60FF
TARGET_TORQUE = 0x6071

# --- controlword commands (bits 0-3 and 7) -------------------------------------------------------
CW_DISABLE_VOLTAGE = 0x00
CW_QUICK_STOP = 0x02
CW_SHUTDOWN = 0x06
CW_SWITCH_ON = 0x07
CW_ENABLE_OPERATION = 0x0F
CW_FAULT_RESET = 0x80

# --- modes of operation (0x6060) -----------------------------------------------------------------
MODES = {"csp": 8, "csv": 9, "cst": 10}
"""The cyclic synchronous modes rtloop drives: position, velocity, torque."""
MODE_NAMES = {code: name for name, code in MODES.items()}
MODE_TARGETS = {8: TARGET_POSITION, 9: TARGET_VELOCITY, 10: TARGET_TORQUE}
"""The target object each mode follows."""


class Cia402State(IntEnum):
    """The drive's state, decoded from its statusword."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


STOPPED_STATES = (Cia402State.SWITCH_ON_DISABLED, Cia402State.FAULT, Cia402State.NOT_READY_TO_SWITCH_ON)
"""Where the safe transition ends: no torque, and nothing more the master asks of the drive."""

_STATE_NAMES = ("not ready to switch on", "switch on disabled", "ready to switch on", "switched on",
                "operation enabled", "quick stop active", "fault reaction active", "fault")

# (mask, value) → state, in the order the standard's table reads them
_DECODE = ((0x4F, 0x00, Cia402State.NOT_READY_TO_SWITCH_ON), (0x4F, 0x40, Cia402State.SWITCH_ON_DISABLED),
           (0x6F, 0x21, Cia402State.READY_TO_SWITCH_ON), (0x6F, 0x23, Cia402State.SWITCHED_ON),
           (0x6F, 0x27, Cia402State.OPERATION_ENABLED), (0x6F, 0x07, Cia402State.QUICK_STOP_ACTIVE),
           (0x4F, 0x0F, Cia402State.FAULT_REACTION_ACTIVE), (0x4F, 0x08, Cia402State.FAULT))


def state_of(statusword: int) -> int:
    """The :class:`Cia402State` (as an int) a statusword says; NOT_READY for a pattern the table lacks."""
    for mask, value, state in _DECODE:
        if statusword & mask == value:
            return int(state)
    return int(Cia402State.NOT_READY_TO_SWITCH_ON)


def state_name(state: int) -> str:
    return _STATE_NAMES[state] if 0 <= state < len(_STATE_NAMES) else f"state {state}"


class StatusBits:
    """Statusword bits a task can wire as readings (1.0 set, 0.0 clear)."""

    FAULT = 1 << 3
    QUICK_STOP = 1 << 5  # 0 = quick stop active (the bit is active low)
    WARNING = 1 << 7
    TARGET_REACHED = 1 << 10
    FOLLOWING_ERROR = 1 << 13  # in CSP; a mode-specific bit


MAX_COUNTS_PER_REV = 1 << 32
GEAR_RATIO_MIN, GEAR_RATIO_MAX = 1e-6, 1e6


@dataclass(frozen=True, slots=True)
class JointScale:
    """Raw drive units ↔ SI units at the joint.

    A position in counts of the motor's encoder becomes joint radians through the encoder's
    counts per motor revolution, the gear ratio (motor revolutions per joint revolution) and the
    direction (+1, or -1 when the joint turns the other way); velocities in counts per second
    alike; torques in per mille of the motor's rated torque (0x6076) become joint N·m."""

    counts_per_rev: float
    gear_ratio: float = 1.0
    direction: int = 1
    rated_torque_Nm: float = 1.0

    @property
    def rad_per_count(self) -> float:
        return self.direction * 2.0 * math.pi / (self.counts_per_rev * self.gear_ratio)

    @property
    def Nm_per_permille(self) -> float:
        return self.direction * self.rated_torque_Nm * self.gear_ratio / 1000.0

    def problem(self) -> str | None:
        """What is wrong with these numbers (one phrase), or None."""
        if not (math.isfinite(self.counts_per_rev) and self.counts_per_rev > 0):
            return f"counts_per_rev must be > 0, got {self.counts_per_rev!r}"
        # an encoder counts whole steps, and the drive model takes them as an int: 2.5 would make the
        # twin (2 counts) and the device (2.5) disagree; past 32 bits no drive's position fits
        if self.counts_per_rev != int(self.counts_per_rev) or self.counts_per_rev > MAX_COUNTS_PER_REV:
            return f"counts_per_rev must be a whole number 1..{MAX_COUNTS_PER_REV}, got {self.counts_per_rev!r}"
        if not (math.isfinite(self.gear_ratio) and self.gear_ratio > 0):
            return f"gear_ratio must be > 0 (motor revolutions per joint revolution), got {self.gear_ratio!r}"
        # bounded so that a count's radians (2π / (counts · gear)) stays a finite, non-zero number:
        # 1e308 made it 0.0, and the first command a division by zero in the loop
        if not GEAR_RATIO_MIN <= self.gear_ratio <= GEAR_RATIO_MAX:
            return (f"gear_ratio must be {GEAR_RATIO_MIN:g}..{GEAR_RATIO_MAX:g} (motor revolutions per joint "
                    f"revolution), got {self.gear_ratio!r}")
        if self.direction not in (1, -1):
            return f"direction must be 1 or -1, got {self.direction!r}"
        if not (math.isfinite(self.rated_torque_Nm) and self.rated_torque_Nm > 0):
            return f"rated_torque_Nm must be > 0, got {self.rated_torque_Nm!r}"
        return None


def to_raw(value: float, per_unit: float, bits: int) -> int:
    """``value`` in SI as the drive's integer (rounded to nearest, ties to even), saturated at a
    signed ``bits``-bit range rather than wrapped to the other sign."""
    raw = value / per_unit
    high = (1 << (bits - 1)) - 1
    if raw >= high:
        return high
    if raw <= -high - 1:
        return -high - 1
    return round(raw)


class JointStateMachine:
    """One drive's CiA 402 state machine as the master drives it: what to write next, from the
    statusword it read last. Holds two ints; no object per call."""

    __slots__ = ("last_controlword", "reset_tries")

    FAULT_RESET_TRIES = 8
    """Fault resets (rising edges) tried on activate before a drive that stays in fault is a fault of the run."""

    def __init__(self) -> None:
        self.last_controlword = CW_DISABLE_VOLTAGE
        self.reset_tries = 0

    def enabling_controlword(self, statusword: int) -> int:
        """The next controlword on the way to *Operation enabled* (one transition per exchange);
        -1 once the drive is there, -2 when a fault will not reset."""
        state = state_of(statusword)
        if state == Cia402State.OPERATION_ENABLED:
            return -1
        if state == Cia402State.FAULT:
            if self.last_controlword & CW_FAULT_RESET:  # the reset is on the rising edge: clear it first
                word = CW_DISABLE_VOLTAGE
            else:
                self.reset_tries += 1
                if self.reset_tries > self.FAULT_RESET_TRIES:
                    return -2
                word = CW_FAULT_RESET
        elif state == Cia402State.SWITCH_ON_DISABLED:
            word = CW_SHUTDOWN
        elif state == Cia402State.READY_TO_SWITCH_ON:
            word = CW_SWITCH_ON
        elif state == Cia402State.SWITCHED_ON:
            word = CW_ENABLE_OPERATION
        elif state == Cia402State.QUICK_STOP_ACTIVE:
            word = CW_DISABLE_VOLTAGE  # out of quick stop through switch on disabled
        else:  # not ready to switch on, fault reaction active: the drive moves on by itself
            word = CW_DISABLE_VOLTAGE
        self.last_controlword = word
        return word

    def stopping_controlword(self, statusword: int) -> int:
        """The next controlword of the safe transition: quick stop while the drive is enabled or
        still braking on its quick-stop ramp, then disable voltage; -1 once the drive is disabled
        (switch on disabled, or in fault)."""
        state = state_of(statusword)
        if state == Cia402State.OPERATION_ENABLED:
            word = CW_QUICK_STOP
        elif state in STOPPED_STATES:
            return -1
        elif state == Cia402State.QUICK_STOP_ACTIVE:
            # the drive sets target reached once its quick-stop ramp has brought it to rest; only
            # then is the voltage taken away (earlier, the joint would coast instead of braking)
            word = CW_DISABLE_VOLTAGE if statusword & StatusBits.TARGET_REACHED else CW_QUICK_STOP
        elif state == Cia402State.FAULT_REACTION_ACTIVE:
            word = CW_DISABLE_VOLTAGE  # the drive brakes by its own fault reaction
        else:  # ready to switch on, switched on: no torque; disable
            word = CW_DISABLE_VOLTAGE
        self.last_controlword = word
        return word

    def running_controlword(self) -> int:
        """While the run goes on: keep operation enabled."""
        self.last_controlword = CW_ENABLE_OPERATION
        return CW_ENABLE_OPERATION
