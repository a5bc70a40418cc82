"""One cycle of a drive device, whatever carries it: commands → outputs, inputs → readings.

:class:`DriveCycle` is the part of a drive device that is the same on the bus and in its twin:
it packs each joint's controlword (from :class:`~rtloop.io.drives.cia402.JointStateMachine`),
mode and target into the drive's outputs, and after the exchange unpacks its inputs into SI
readings and checks them (a drive that left *Operation enabled* is a named fault). The EtherCAT
device binds it to its frame's bytes, the twin to an in-process exchange with the emulated
drives: both run this same code, so a run equals its simulation bit for bit.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from rtloop.errors import DeviceFault
from rtloop.io.drives import cia402
from rtloop.io.drives.cia402 import Cia402State, JointStateMachine, StatusBits, state_name, state_of, to_raw
from rtloop.io.drives.joints import JointConfig

__all__ = ["ENABLE_LIMIT", "DriveCycle", "command_names", "reading_names"]

ENABLE_LIMIT = 1000
"""Exchanges a drive may take from activate to *Operation enabled* before that is a fault."""
MODE_LIMIT = 50
"""Exchanges a drive may take to show a mode it was asked for (0x6061) before that is a fault."""

_COMMANDS = ((8, "target_position_rad"), (9, "target_velocity_rad_s"), (10, "target_torque_Nm"))
_READING_FLAGS = (("enabled", 0), ("fault", StatusBits.FAULT), ("warning", StatusBits.WARNING),
                  ("target_reached", StatusBits.TARGET_REACHED), ("following_error", StatusBits.FOLLOWING_ERROR),
                  ("quick_stop", StatusBits.QUICK_STOP))


def command_names(joint: JointConfig) -> list[str]:
    names = [f"{joint.name}_{suffix}" for mode, suffix in _COMMANDS if mode in joint.modes]
    if joint.mode_command:
        names.append(f"{joint.name}_target_mode")
    return names


def reading_names(joint: JointConfig) -> list[str]:
    names = [f"{joint.name}_position_rad"]
    if cia402.VELOCITY_ACTUAL in joint.tx:
        names.append(f"{joint.name}_velocity_rad_s")
    if cia402.TORQUE_ACTUAL in joint.tx:
        names.append(f"{joint.name}_torque_Nm")
    names += [f"{joint.name}_{flag}" for flag, _ in _READING_FLAGS]
    if cia402.ERROR_CODE in joint.tx:
        names.append(f"{joint.name}_error_code")
    if cia402.MODES_DISPLAY in joint.tx:
        names.append(f"{joint.name}_mode")
    return names


class _Joint:
    """Per joint: where its values are, its state machine, what it read last."""

    __slots__ = ("config", "in_at", "machine", "mode", "mode_asked_at", "out_at", "out_values", "position_raw",
                 "rx", "statusword", "tx", "u_at", "u_mode", "u_position", "u_torque", "u_velocity", "y_at")

    def __init__(self, config: JointConfig, u_at: int, y_at: int) -> None:
        self.config = config
        self.machine = JointStateMachine()
        self.rx = config.rx
        self.tx = config.tx
        self.statusword = 0
        self.position_raw = 0
        self.mode = config.modes[0]
        self.mode_asked_at = 0
        at = u_at
        self.u_position = self.u_velocity = self.u_torque = self.u_mode = -1
        for mode, _suffix in _COMMANDS:
            if mode in config.modes:
                if mode == 8:
                    self.u_position = at
                elif mode == 9:
                    self.u_velocity = at
                else:
                    self.u_torque = at
                at += 1
        if config.mode_command:
            self.u_mode = at
        self.u_at, self.y_at = u_at, y_at
        self.out_values = [0] * len(config.rx.objects)  # rewritten in place each cycle, packed in one call
        self.out_at = self.in_at = 0


class DriveCycle:
    """The joints of one drive device, bound to where their outputs and inputs live."""

    def __init__(self, device: str, joints: Sequence[JointConfig]) -> None:
        self.device = device
        self.joints: list[_Joint] = []
        u_at = y_at = 0
        for config in joints:
            self.joints.append(_Joint(config, u_at, y_at))
            u_at += len(command_names(config))
            y_at += len(reading_names(config))
        self.out_buffer: Any = None
        self.in_buffer: Any = None
        self.enabled = False
        self.exchanges = 0
        """Exchanges since activate (named in faults: the drive's cycle)."""

    @property
    def output_bytes(self) -> int:
        return sum(joint.rx.size for joint in self.joints)

    @property
    def input_bytes(self) -> int:
        return sum(joint.tx.size for joint in self.joints)

    def bind(self, out_buffer: Any, out_at: int, in_buffer: Any, in_at: int) -> None:
        """Outputs of joint after joint from ``out_buffer[out_at]``, inputs from ``in_buffer[in_at]``
        (SOEM's layout: every slave's outputs, then every slave's inputs)."""
        self.out_buffer, self.in_buffer = out_buffer, in_buffer
        for joint in self.joints:
            joint.out_at, joint.in_at = out_at, in_at
            out_at += joint.rx.size
            in_at += joint.tx.size

    def where(self, joint: _Joint) -> str:
        config = joint.config
        return f"devices.{self.device}: joint {config.name!r} (slave {config.slave}, {config.identity.describe()})"

    # --- before the exchange ----------------------------------------------------------------------
    def safe_outputs(self) -> bool:
        """The next step of the safe transition for every joint; True once all are disabled."""
        done = True
        for joint in self.joints:
            word = joint.machine.stopping_controlword(joint.statusword)
            if word < 0:
                word = cia402.CW_DISABLE_VOLTAGE
            else:
                done = False
            self._pack(joint, word, joint.mode, joint.position_raw, 0, 0)
        return done

    def prepare_outputs(self, u: Any) -> None:
        """Controlwords, modes and targets for this cycle's exchange (``u``: the device's commands)."""
        for joint in self.joints:
            if self.enabled:
                word = joint.machine.running_controlword()
            else:
                word = joint.machine.enabling_controlword(joint.statusword)
                if word == -2:
                    raise self._fault(joint, "the drive stays in fault after "
                                      f"{JointStateMachine.FAULT_RESET_TRIES} fault resets")
                if word == -1:
                    word = cia402.CW_ENABLE_OPERATION
            scale = joint.config.scale
            if joint.u_mode >= 0:
                mode = round(float(u[joint.u_mode]))
                if mode != joint.mode:
                    if mode not in joint.config.modes:
                        raise self._fault(joint, f"mode command {float(u[joint.u_mode])!r} is not one of the joint's "
                                          f"modes {list(joint.config.modes)}")
                    joint.mode = mode
                    joint.mode_asked_at = self.exchanges
            operating = self.enabled
            position = to_raw(float(u[joint.u_position]), scale.rad_per_count, 32) \
                if operating and joint.u_position >= 0 and joint.mode == 8 else joint.position_raw
            velocity = to_raw(float(u[joint.u_velocity]), scale.rad_per_count, 32) \
                if operating and joint.u_velocity >= 0 and joint.mode == 9 else 0
            torque = to_raw(float(u[joint.u_torque]), scale.Nm_per_permille, 16) \
                if operating and joint.u_torque >= 0 and joint.mode == 10 else 0
            self._pack(joint, word, joint.mode, position, velocity, torque)

    def _pack(self, joint: _Joint, controlword: int, mode: int, position: int, velocity: int, torque: int) -> None:
        values, rx = joint.out_values, joint.rx.position
        for index, value in ((cia402.CONTROLWORD, controlword), (cia402.MODES_OF_OPERATION, mode),
                             (cia402.TARGET_POSITION, position), (cia402.TARGET_VELOCITY, velocity),
                             (cia402.TARGET_TORQUE, torque)):
            place = rx.get(index, -1)
            if place >= 0:
                values[place] = value
        joint.rx.struct.pack_into(self.out_buffer, joint.out_at, *values)

    # --- after the exchange -----------------------------------------------------------------------
    def take_inputs(self, y: Any, check: bool = True) -> None:
        """Unpack every joint's inputs into ``y`` (SI) and, with ``check``, fault on a drive that is not
        where the run needs it."""
        all_enabled = True
        for joint in self.joints:
            values = joint.tx.struct.unpack_from(self.in_buffer, joint.in_at)
            tx = joint.tx.position
            statusword = joint.statusword = values[tx[cia402.STATUSWORD]]
            joint.position_raw = values[tx[cia402.POSITION_ACTUAL]]
            scale = joint.config.scale
            state = state_of(statusword)
            at = joint.y_at
            y[at] = joint.position_raw * scale.rad_per_count
            at += 1
            place = tx.get(cia402.VELOCITY_ACTUAL, -1)
            if place >= 0:
                y[at] = values[place] * scale.rad_per_count
                at += 1
            place = tx.get(cia402.TORQUE_ACTUAL, -1)
            if place >= 0:
                y[at] = values[place] * scale.Nm_per_permille
                at += 1
            y[at] = 1.0 if state == Cia402State.OPERATION_ENABLED else 0.0
            y[at + 1] = 1.0 if statusword & StatusBits.FAULT else 0.0
            y[at + 2] = 1.0 if statusword & StatusBits.WARNING else 0.0
            y[at + 3] = 1.0 if statusword & StatusBits.TARGET_REACHED else 0.0
            y[at + 4] = 1.0 if statusword & StatusBits.FOLLOWING_ERROR and joint.mode == 8 else 0.0
            y[at + 5] = 1.0 if state == Cia402State.QUICK_STOP_ACTIVE else 0.0
            at += 6
            place = tx.get(cia402.ERROR_CODE, -1)
            if place >= 0:
                y[at] = float(values[place])
                at += 1
            place = tx.get(cia402.MODES_DISPLAY, -1)
            if place >= 0:
                y[at] = float(values[place])
                if check and values[place] != joint.mode and self.exchanges - joint.mode_asked_at > MODE_LIMIT:
                    raise self._fault(joint, f"the drive shows mode {values[place]} (0x6061), not the "
                                      f"{cia402.MODE_NAMES.get(joint.mode, joint.mode)} it was asked for "
                                      f"{self.exchanges - joint.mode_asked_at} exchanges ago: it does not support it")
            if state != Cia402State.OPERATION_ENABLED:
                all_enabled = False
                if check and self.enabled:
                    raise self._fault(joint, self._left_operation(joint, values))
        if check:
            self.exchanges += 1
            if not self.enabled:
                if all_enabled:
                    self.enabled = True
                elif self.exchanges > ENABLE_LIMIT:
                    waiting = [j for j in self.joints if state_of(j.statusword) != Cia402State.OPERATION_ENABLED]
                    raise self._fault(waiting[0], f"not in operation enabled after {ENABLE_LIMIT} exchanges: "
                                      f"{state_name(state_of(waiting[0].statusword))}")

    def _left_operation(self, joint: _Joint, values: tuple[Any, ...]) -> str:
        statusword = joint.statusword
        place = joint.tx.position.get(cia402.ERROR_CODE, -1)
        code = f", error code 0x{values[place]:04X} (0x603F)" if place >= 0 else ""
        what = "drive fault" if statusword & StatusBits.FAULT else "the drive left operation enabled"
        return f"{what}: statusword 0x{statusword:04X} (0x6041: {state_name(state_of(statusword))}){code}"

    def _fault(self, joint: _Joint, problem: str) -> DeviceFault:
        return DeviceFault(f"{self.where(joint)}: {problem}, exchange {self.exchanges}")
