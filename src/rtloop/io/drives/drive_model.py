"""An emulated CiA 402 servo drive: the drive's own state machine, its control loops and a motor
with a load, stepped once per process-data exchange.

It stands behind the emulated EtherCAT slave's process data (``io/drives/esc.py``) and, unchanged,
in the device's twin (``rtloop simulate``): the same Python floats in the same order, so a real
run against the emulator equals its simulation bit for bit. Each :meth:`DriveModel.exchange` is
one cycle of the drive: it takes the objects the master wrote (controlword, mode, targets) and
moves the motor one step ``cycle_s``; the objects the master reads are those of the step before
(an ESC hands the master the inputs it holds when the frame passes, then the drive computes).

Motor and load (motor side, Euler in 20-sim's order: integrate with the last rates, then
evaluate)::

    J·dω/dt = τ − b·ω,   dθ/dt = ω,   τ clamped to ±torque_max_Nm

Loops: CSP a 20-sim PID on the position error (``kp·(1 + τD·s)/(1 + β·τD·s)·(1 + 1/(τI·s))``,
error in motor radians, output in N·m); CSV a proportional velocity loop; CST the target torque
itself. Quick stop brakes at ``quick_stop_torque_Nm`` to rest, then holds *quick stop active*
with target reached set (quick stop option code 6). A fault (injected, or a following error
beyond ``following_error_window`` counts in CSP) goes through *fault reaction active* (braking)
to *fault*; a rising edge of controlword bit 7 resets it.

:func:`emulated_drive` gives the emulator its compiled twin (``io/devio_c/esc_drive.c``: the same
arithmetic in the same order, with the same methods and attributes) where ``rtloop.io._devio`` is
built, so the emulated slaves' process data runs without Python; the twin of ``rtloop simulate``
keeps this reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rtloop.io import compiled
from rtloop.io.drives.cia402 import (
    MODE_NAMES,
    Cia402State,
    StatusBits,
)

__all__ = ["DriveModel", "DriveParameters", "emulated_drive"]

FOLLOWING_ERROR_CODE = 0x8611
"""CiA 402's error code for a following error (0x603F)."""
INJECTED_FAULT_CODE = 0x5530
"""The error code of an injected drive fault (a hardware fault of the drive's power stage, say)."""
OUTPUTS_LOST_CODE = 0x8700
"""The error code when the EtherCAT slave left OP with the drive enabled (sync manager watchdog)."""

_SW_BY_STATE = {Cia402State.NOT_READY_TO_SWITCH_ON: 0x0000, Cia402State.SWITCH_ON_DISABLED: 0x0040,
                Cia402State.READY_TO_SWITCH_ON: 0x0021, Cia402State.SWITCHED_ON: 0x0023,
                Cia402State.OPERATION_ENABLED: 0x0027, Cia402State.QUICK_STOP_ACTIVE: 0x0007,
                Cia402State.FAULT_REACTION_ACTIVE: 0x000F, Cia402State.FAULT: 0x0008}
_VOLTAGE_ENABLED = 0x0010
_REMOTE = 0x0200
_FOLLOWS_COMMAND = 0x1000


@dataclass(frozen=True)
class DriveParameters:
    """One emulated drive: its encoder, its motor and load, its loops, its limits."""

    cycle_s: float = 0.001
    """The drive's cycle: one model step per process-data exchange (the master's period)."""
    counts_per_rev: int = 4096
    inertia_kgm2: float = 2e-5
    """Motor and load, reflected to the motor shaft."""
    damping_Nms: float = 1e-5
    torque_max_Nm: float = 0.5
    rated_torque_Nm: float = 0.2
    """What 1000 ‰ of a torque object (0x6071, 0x6077) is."""
    kp_Nm_per_rad: float = 0.02
    """CSP: the PID's gain on the position error (motor radians → N·m)."""
    tau_d_s: float = 0.01
    beta: float = 0.1
    tau_i_s: float = 1000.0
    kv_Nms: float = 0.002
    """CSV: velocity loop gain (rad/s error → N·m)."""
    quick_stop_torque_Nm: float = 0.3
    following_error_window: int = 1 << 20
    """Counts of following error in CSP beyond which the drive faults (0x6065)."""
    modes: tuple[int, ...] = (8, 9, 10)
    """Modes the drive supports (0x6502): a mode outside them is not taken (0x6061 keeps the old)."""

    def problem(self) -> str | None:
        for name in ("cycle_s", "inertia_kgm2", "torque_max_Nm", "rated_torque_Nm", "tau_d_s", "beta", "tau_i_s",
                     "quick_stop_torque_Nm"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                return f"{name} must be a number > 0, got {value!r}"
        for name in ("damping_Nms", "kp_Nm_per_rad", "kv_Nms"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                return f"{name} must be a number ≥ 0, got {value!r}"
        if not (isinstance(self.counts_per_rev, int) and self.counts_per_rev > 0):
            return f"counts_per_rev must be an integer > 0, got {self.counts_per_rev!r}"
        return None


def _wrap32(value: int) -> int:
    return (value + (1 << 31)) % (1 << 32) - (1 << 31)


def _saturate(value: float, bits: int) -> int:
    high = (1 << (bits - 1)) - 1
    if value >= high:
        return high
    if value <= -high - 1:
        return -high - 1
    return round(value)


class DriveModel:
    """One drive. The master's objects go in through :meth:`exchange`; the objects it reads are
    the attributes ``statusword``, ``mode_display``, ``position``, ``velocity``, ``torque``,
    ``following_error`` and ``error_code`` (raw CiA 402 units)."""

    def __init__(self, parameters: DriveParameters | None = None) -> None:
        p = self.p = parameters or DriveParameters()
        self.rad_per_count = 2.0 * math.pi / p.counts_per_rev
        # the drive boots through "not ready to switch on" into "switch on disabled" by itself
        self.state = Cia402State.SWITCH_ON_DISABLED
        self.mode = 8
        self.theta = self.omega = self.torque_Nm = 0.0  # motor angle [rad], speed [rad/s], torque [N·m]
        self.rate_theta = self.rate_omega = 0.0
        self.pd_state = self.pi_state = 0.0
        self.rate_pd = self.rate_pi = 0.0
        self.last_controlword = 0
        self.error_code = 0
        self.pending_fault = 0
        self.target_position = 0
        self.quick_stop_done = False
        self.events: list[str] = []
        """What happened that a log should say (state changes, faults), taken by the caller."""
        self._publish(0)

    # --- the master's side ------------------------------------------------------------------------
    def inject_fault(self, code: int = INJECTED_FAULT_CODE) -> None:
        """A fault of the drive itself (a power stage fault, an over-temperature) at the next step."""
        self.pending_fault = code

    def outputs_lost(self) -> None:
        """The bus stopped carrying valid outputs (the slave left OP): an enabled drive quick-stops."""
        if self.state == Cia402State.OPERATION_ENABLED:
            self._enter(Cia402State.QUICK_STOP_ACTIVE, "quick stop (outputs no longer valid: the slave left OP)")

    def exchange(self, controlword: int, mode: int, target_position: int, target_velocity: int,
                 target_torque: int, outputs_valid: bool = True) -> None:
        """One cycle: the objects the master wrote (when ``outputs_valid``: the slave is in OP),
        then one step of the loops and the motor."""
        if outputs_valid:
            self._state_machine(controlword)
            if mode != self.mode and self.state != Cia402State.FAULT and mode in self.p.modes:
                self.events.append(f"mode {MODE_NAMES.get(self.mode, self.mode)} -> {MODE_NAMES.get(mode, mode)}")
                self.mode = mode
                self.pd_state = self.pi_state = 0.0  # a mode change starts its loop afresh
        else:
            self.outputs_lost()
        if self.pending_fault:
            self._fault(self.pending_fault, "drive fault injected")
            self.pending_fault = 0
        self._step(target_position, target_velocity, target_torque)

    # --- the drive's inside -----------------------------------------------------------------------
    def _enter(self, state: Cia402State, why: str) -> None:
        if state != self.state:
            self.state = state
            self.quick_stop_done = False
            self.events.append(why)

    def _fault(self, code: int, why: str) -> None:
        if self.state not in (Cia402State.FAULT, Cia402State.FAULT_REACTION_ACTIVE):
            self.error_code = code
            self._enter(Cia402State.FAULT_REACTION_ACTIVE, f"fault 0x{code:04X}: {why}")

    def _state_machine(self, controlword: int) -> None:
        state = self.state
        rising_reset = controlword & 0x80 and not self.last_controlword & 0x80
        self.last_controlword = controlword
        command = controlword & 0x8F
        voltage = controlword & 0x02
        quick = voltage and not controlword & 0x04  # quick stop: bit 1 set, bit 2 clear
        if state == Cia402State.FAULT:
            if rising_reset:
                self.error_code = 0
                self._enter(Cia402State.SWITCH_ON_DISABLED, "fault reset")
            return
        if state == Cia402State.FAULT_REACTION_ACTIVE:
            return
        if not voltage:
            self._enter(Cia402State.SWITCH_ON_DISABLED, "switch on disabled (disable voltage)")
        elif state == Cia402State.OPERATION_ENABLED and quick:
            self._enter(Cia402State.QUICK_STOP_ACTIVE, "quick stop (controlword)")
        elif quick:
            if state != Cia402State.QUICK_STOP_ACTIVE:
                self._enter(Cia402State.SWITCH_ON_DISABLED, "switch on disabled (quick stop)")
        elif state == Cia402State.SWITCH_ON_DISABLED and command & 0x87 == 0x06:
            self._enter(Cia402State.READY_TO_SWITCH_ON, "ready to switch on")
        elif state == Cia402State.READY_TO_SWITCH_ON and command & 0x87 == 0x07:
            self._enter(Cia402State.SWITCHED_ON, "switched on")
        elif state == Cia402State.SWITCHED_ON and command == 0x0F:
            self.pd_state = self.pi_state = 0.0
            self._enter(Cia402State.OPERATION_ENABLED, f"operation enabled ({MODE_NAMES.get(self.mode, self.mode)})")
        elif state == Cia402State.SWITCHED_ON and command & 0x87 == 0x06:
            self._enter(Cia402State.READY_TO_SWITCH_ON, "ready to switch on (shutdown)")
        elif state == Cia402State.OPERATION_ENABLED and command & 0x8F == 0x07:
            self._enter(Cia402State.SWITCHED_ON, "switched on (disable operation)")
        elif state == Cia402State.OPERATION_ENABLED and command & 0x87 == 0x06:
            self._enter(Cia402State.READY_TO_SWITCH_ON, "ready to switch on (shutdown)")

    def _brake_torque(self) -> float:
        """Towards rest at the quick-stop torque, never past it within a step."""
        p = self.p
        stop = p.inertia_kgm2 * self.omega / p.cycle_s  # the torque that stops the motor in one step
        return -max(-p.quick_stop_torque_Nm, min(p.quick_stop_torque_Nm, stop))

    def _step(self, target_position: int, target_velocity: int, target_torque: int) -> None:
        p = self.p
        h = p.cycle_s
        # integrate with the rates of the last evaluation (20-sim's Euler order)
        self.theta += h * self.rate_theta
        self.omega += h * self.rate_omega
        self.pd_state += h * self.rate_pd
        self.pi_state += h * self.rate_pi
        self.rate_pd = self.rate_pi = 0.0
        state = self.state
        torque = 0.0
        following = 0
        if state == Cia402State.OPERATION_ENABLED:
            if self.mode == 8:
                following = target_position - _wrap32(round(self.theta / self.rad_per_count))
                error = following * self.rad_per_count
                pd_out = self.pd_state + p.kp_Nm_per_rad * error / p.beta
                self.rate_pd = (p.kp_Nm_per_rad * error - pd_out) / (p.beta * p.tau_d_s)
                self.rate_pi = pd_out / p.tau_i_s
                torque = self.pi_state + pd_out
                if abs(following) > p.following_error_window:
                    self._fault(FOLLOWING_ERROR_CODE, f"following error {following} counts "
                                f"(window {p.following_error_window})")
            elif self.mode == 9:
                torque = p.kv_Nms * (target_velocity * self.rad_per_count - self.omega)
            elif self.mode == 10:
                torque = target_torque * p.rated_torque_Nm / 1000.0
        elif state in (Cia402State.QUICK_STOP_ACTIVE, Cia402State.FAULT_REACTION_ACTIVE):
            torque = self._brake_torque()
        saturated = abs(torque) > p.torque_max_Nm
        torque = max(-p.torque_max_Nm, min(p.torque_max_Nm, torque))
        self.torque_Nm = torque
        self.rate_theta = self.omega
        self.rate_omega = (torque - p.damping_Nms * self.omega) / p.inertia_kgm2
        at_rest = abs(self.omega) * h < self.rad_per_count and abs(self.rate_omega) * h * h < self.rad_per_count
        if state == Cia402State.FAULT_REACTION_ACTIVE and at_rest:
            self._enter(Cia402State.FAULT, f"fault (error code 0x{self.error_code:04X}), drive at rest")
        elif state == Cia402State.QUICK_STOP_ACTIVE and at_rest and not self.quick_stop_done:
            self.quick_stop_done = True
            self.events.append("quick stop done: at rest")
        self.target_position = target_position
        self._publish(following, saturated, at_rest)

    def _publish(self, following: int, saturated: bool = False, at_rest: bool = True) -> None:
        state = self.state
        word = _SW_BY_STATE[state]
        if state not in (Cia402State.SWITCH_ON_DISABLED, Cia402State.NOT_READY_TO_SWITCH_ON):
            word |= _VOLTAGE_ENABLED
        word |= _REMOTE
        if saturated:
            word |= StatusBits.WARNING  # the torque is at its limit: the drive cannot follow as asked
        if state == Cia402State.OPERATION_ENABLED:
            word |= _FOLLOWS_COMMAND
            if self.mode == 8 and abs(following) > self.p.following_error_window // 2:
                word |= StatusBits.FOLLOWING_ERROR
            if self.mode == 8 and abs(following) <= 16 and at_rest:
                word |= StatusBits.TARGET_REACHED
        elif state == Cia402State.QUICK_STOP_ACTIVE and at_rest:
            word |= StatusBits.TARGET_REACHED  # the quick stop has ended: at rest
        self.statusword = word
        self.mode_display = self.mode
        self.position = _wrap32(round(self.theta / self.rad_per_count))
        self.velocity = _saturate(self.omega / self.rad_per_count, 32)
        self.torque = _saturate(self.torque_Nm / self.p.rated_torque_Nm * 1000.0, 16)
        self.following_error = _wrap32(following)


def emulated_drive(parameters: DriveParameters | None = None, use_compiled: bool = True) -> DriveModel:
    """A drive for the emulated slaves: the compiled twin of :class:`DriveModel` where the devices'
    C code is built (and ``use_compiled``), else the reference itself."""
    module = compiled.devio() if use_compiled else None
    if module is None:
        return DriveModel(parameters)
    drive: DriveModel = module.EmulatedDrive(parameters or DriveParameters(), MODE_NAMES, tuple(Cia402State))
    return drive
