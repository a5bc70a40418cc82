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

import numpy as np

from rtloop.errors import DeviceFault
from rtloop.io.bytelayout import FloatView
from rtloop.io.drives import cia402
from rtloop.io.drives.cia402 import Cia402State, JointStateMachine, StatusBits, state_name, state_of, to_raw
from rtloop.io.drives.joints import JointConfig

__all__ = ["ENABLE_LIMIT", "NOT_LINKED", "DriveCycle", "command_names", "reading_names"]

ENABLE_LIMIT = 1000
"""Exchanges a drive may take from activate to *Operation enabled* before that is a fault."""
MODE_LIMIT = 50
NOT_LINKED = -3
DC_LOST = -4
""":meth:`DriveCycle.receive_linked`: every slave exchanged, but the DC datagram's working counter is wrong."""
""":meth:`DriveCycle.receive_linked`: the C cycle does not run now; the transport receives and the reference takes."""
"""Exchanges a drive may take to show a mode it was asked for (0x6061) before that is a fault."""

_COMMANDS = ((8, "target_position_rad"), (9, "target_velocity_rad_s"), (10, "target_torque_Nm"))
_READING_FLAGS = (("enabled", 0), ("fault", StatusBits.FAULT), ("warning", StatusBits.WARNING),
                  ("target_reached", StatusBits.TARGET_REACHED), ("following_error", StatusBits.FOLLOWING_ERROR),
                  ("quick_stop", StatusBits.QUICK_STOP))


_STATES = tuple(state_of(bits) for bits in range(0x70))
"""Statusword bits 0-3, 5 and 6 (``& 0x6F``) → the state: one index instead of the standard's table."""
_ENABLED, _QUICK_STOP = int(Cia402State.OPERATION_ENABLED), int(Cia402State.QUICK_STOP_ACTIVE)
_FAULT, _WARNING = StatusBits.FAULT, StatusBits.WARNING  # module names: one lookup less each, every cycle
_TARGET_REACHED, _FOLLOWING_ERROR = StatusBits.TARGET_REACHED, StatusBits.FOLLOWING_ERROR


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

    __slots__ = ("config", "in_at", "machine", "mode", "mode_asked_at", "out_at", "out_values", "pack", "position_raw",
                 "rad_per_count", "rx", "rx_controlword", "rx_mode", "rx_position", "rx_torque", "rx_velocity",
                 "statusword", "torque_per_permille", "tx", "tx_error", "tx_mode", "tx_position", "tx_status",
                 "tx_torque", "tx_velocity", "u_at", "u_mode", "u_position", "u_torque", "u_velocity", "unpack",
                 "y_at")

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
        # where each object sits among the values packed and unpacked (-1: not mapped), looked up once
        rx, tx = config.rx.position, config.tx.position
        self.rx_controlword, self.rx_mode = rx[cia402.CONTROLWORD], rx[cia402.MODES_OF_OPERATION]
        self.rx_position, self.rx_velocity = rx.get(cia402.TARGET_POSITION, -1), rx.get(cia402.TARGET_VELOCITY, -1)
        self.rx_torque = rx.get(cia402.TARGET_TORQUE, -1)
        self.tx_status, self.tx_position = tx[cia402.STATUSWORD], tx[cia402.POSITION_ACTUAL]
        self.tx_velocity, self.tx_torque = tx.get(cia402.VELOCITY_ACTUAL, -1), tx.get(cia402.TORQUE_ACTUAL, -1)
        self.tx_error, self.tx_mode = tx.get(cia402.ERROR_CODE, -1), tx.get(cia402.MODES_DISPLAY, -1)
        self.pack, self.unpack = config.rx.struct.pack_into, config.tx.struct.unpack_from
        self.rad_per_count, self.torque_per_permille = config.scale.rad_per_count, config.scale.Nm_per_permille


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
        self._u, self._y = FloatView(), FloatView()  # memoryviews of the task's vectors: no numpy scalars
        self.out_buffer: Any = None
        self.in_buffer: Any = None
        self.enabled = False
        self.exchanges = 0
        """Exchanges since activate (named in faults: the drive's cycle)."""
        self._fast: Any = None  # the running cycle in C (io/devio_c/drive.c DriveRun), once every drive is enabled
        self._fast_u: Any = None
        self._fast_y: Any = None
        self._fast_used = False
        self._last_u: Any = None
        self._tried: tuple[Any, Any] = (None, None)  # the (u, y) the C cycle was last built for, or tried
        self._link: tuple[Any, ...] | None = None  # what DriveRun.link takes (link())
        self._sent_linked = False  # the last frame went out through send_linked (its answer is C's to take)
        from rtloop.io.compiled import devio

        self._devio = devio()  # looked up here, before T0: the lookup reads and checksums the C sources

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
        self._fast = None
        self._tried = (None, None)
        for joint in self.joints:
            joint.out_at, joint.in_at = out_at, in_at
            out_at += joint.rx.size
            in_at += joint.tx.size

    def link(self, fd: int, frame: bytearray, reply: bytearray, wkc_at: int, expected_wkc: int,
             timeout_ns: int, dc_wkc_at: int = 0, expected_dc_wkc: int = 0, precise: bool = False) -> None:
        """The EtherCAT frame the buffers are places in, on the raw socket ``fd`` (blocking, its
        receive timeout one tick), its answer due within ``timeout_ns`` of the send: the running
        cycle then packs, sends, receives, checks and unpacks in one C call each way
        (:meth:`send_linked`, :meth:`receive_linked`; ``EthercatDevice._send`` and ``_receive`` are
        the reference). ``dc_wkc_at``: where the DC datagram's working counter is (0: none), checked
        against ``expected_dc_wkc`` once every slave exchanged (:data:`DC_LOST` when it differs).
        ``precise``: the wait ends at the timeout to the nanosecond (ppoll, one syscall more a cycle;
        lost frames tolerated, a lost one ends its cycle in time)."""
        self._link = (fd, frame, reply, wkc_at, expected_wkc, timeout_ns, dc_wkc_at, expected_dc_wkc, precise)

    def send_linked(self, u: Any) -> bool:
        """The running cycle's outputs packed and the frame sent, in C: True; False when the C
        cycle does not run now (the enabling, a mode change): nothing was sent."""
        fast = self._fast
        if fast is not None and u is self._fast_u and self.enabled and self._link is not None and fast.send() < 0:
            self._fast_used = self._sent_linked = True
            return True
        self._sent_linked = False
        return False

    def linked_sent_at(self) -> float:
        """When :meth:`send_linked` last sent (``time.monotonic``'s clock; 0.0: never)."""
        return self._fast.sent_ns * 1e-9 if self._fast is not None and self._link is not None else 0.0

    def receive_linked(self, y: Any) -> int:
        """The answer to the frame :meth:`send_linked` sent, checked and taken into ``y`` in C: -1.
        -2: no answer within the timeout. ``NOT_LINKED``: the C cycle does not run now (the caller
        receives). ``DC_LOST``: the DC datagram's working counter is wrong (inputs not taken). Else
        the answer's working counter, its inputs not taken (the caller checks it, then
        :meth:`take_inputs` names what the C cycle did not take)."""
        fast = self._fast
        if not self._sent_linked or y is not self._fast_y:
            return NOT_LINKED
        got: int = fast.receive()
        if got == -1:
            self._fast_used = True
            self.exchanges += 1
        return got

    def count_lost(self) -> None:
        """A cycle whose frame did not come back (``lost_frames_max``): an exchange all the same (named
        in faults; the enabling's limit), but none a drive could show a mode in: the wait for a mode
        asked for (``MODE_LIMIT``) does not run on, or a run of lost frames after a mode change is a
        false 'does not support it' at the first frame back; nor is a fault reset it carried one of
        the tries (``FAULT_RESET_TRIES``): lost frames while a drive resets were a false 'stays in
        fault'."""
        self.exchanges += 1
        for joint in self.joints:
            joint.mode_asked_at += 1
            if joint.machine.last_controlword & cia402.CW_FAULT_RESET:  # nor one of its fault resets tried
                joint.machine.reset_tries -= 1

    def where(self, joint: _Joint) -> str:
        config = joint.config
        return f"devices.{self.device}: joint {config.name!r} (slave {config.slave}, {config.identity.describe()})"

    # --- before the exchange ----------------------------------------------------------------------
    def safe_outputs(self) -> bool:
        """The next step of the safe transition for every joint; True once all are disabled."""
        self._from_fast()
        done = True
        for joint in self.joints:
            word = joint.machine.stopping_controlword(joint.statusword)
            if word < 0:
                word = cia402.CW_DISABLE_VOLTAGE
            else:
                done = False
            self._pack(joint, word, joint.mode, joint.position_raw, 0, 0)
        return done

    def still_stopping(self) -> str:
        """The joints the safe transition has not brought to a stop yet, as last read (each named
        with its state and statusword); empty once all are."""
        self._from_fast()
        return ", ".join(f"joint {joint.config.name!r} in {state_name(state_of(joint.statusword))} (statusword "
                         f"0x{joint.statusword:04X})"
                         for joint in self.joints if state_of(joint.statusword) not in cia402.STOPPED_STATES)

    def waiting_outputs(self) -> None:
        """The outputs while the slaves wait for T0 in OP: disable voltage (the drives stay disabled),
        each joint's first mode, no target."""
        for joint in self.joints:
            self._pack(joint, cia402.CW_DISABLE_VOLTAGE, joint.mode, joint.position_raw, 0, 0)

    def prepare_outputs(self, u: Any) -> None:
        """Controlwords, modes and targets for this cycle's exchange (``u``: the device's commands)."""
        fast = self._fast
        if fast is not None and u is self._fast_u and self.enabled and fast.prepare() < 0:
            self._fast_used = True
            return
        self._from_fast()
        self._last_u = u
        self._prepare_reference(u)
        if self._fast is not None:
            modes = self._modes
            for i, joint in enumerate(self.joints):
                modes[i] = joint.mode

    def _prepare_reference(self, u: Any) -> None:
        u = self._u.of(u)
        enabled = self.enabled
        for joint in self.joints:
            if enabled:
                word = cia402.CW_ENABLE_OPERATION
            else:
                word = joint.machine.enabling_controlword(joint.statusword)
                if word == -2:
                    raise self._fault(joint, "the drive stays in fault after "
                                      f"{JointStateMachine.FAULT_RESET_TRIES} fault resets")
                if word == -1:
                    word = cia402.CW_ENABLE_OPERATION
            if joint.u_mode >= 0:
                mode = round(u[joint.u_mode])
                if mode != joint.mode:
                    if mode not in joint.config.modes:
                        raise self._fault(joint, f"mode command {u[joint.u_mode]!r} is not one of the joint's "
                                          f"modes {list(joint.config.modes)}")
                    joint.mode = mode
                    joint.mode_asked_at = self.exchanges
            mode = joint.mode
            values = joint.out_values
            values[joint.rx_controlword] = word
            values[joint.rx_mode] = mode
            if joint.rx_position >= 0:  # a joint not in CSP, or not enabled yet, holds where it is
                values[joint.rx_position] = to_raw(u[joint.u_position], joint.rad_per_count, 32) \
                    if enabled and mode == 8 else joint.position_raw
            if joint.rx_velocity >= 0:
                values[joint.rx_velocity] = to_raw(u[joint.u_velocity], joint.rad_per_count, 32) \
                    if enabled and mode == 9 else 0
            if joint.rx_torque >= 0:
                values[joint.rx_torque] = to_raw(u[joint.u_torque], joint.torque_per_permille, 16) \
                    if enabled and mode == 10 else 0
            joint.pack(self.out_buffer, joint.out_at, *values)

    def _pack(self, joint: _Joint, controlword: int, mode: int, position: int, velocity: int, torque: int) -> None:
        values = joint.out_values
        values[joint.rx_controlword] = controlword
        values[joint.rx_mode] = mode
        for place, value in ((joint.rx_position, position), (joint.rx_velocity, velocity), (joint.rx_torque, torque)):
            if place >= 0:
                values[place] = value
        joint.pack(self.out_buffer, joint.out_at, *values)

    # --- after the exchange -----------------------------------------------------------------------
    def take_inputs(self, y: Any, check: bool = True) -> None:
        """Unpack every joint's inputs into ``y`` (SI) and, with ``check``, fault on a drive that is not
        where the run needs it."""
        if check and self.enabled:
            fast = self._fast
            tried_u, tried_y = self._tried
            if (fast is None or y is not self._fast_y) and (tried_u is not self._last_u or tried_y is not y):
                fast = self._compiled(y)  # in the loop only where compile() was not called before T0
            if fast is not None and fast.take() < 0:
                self._fast_used = True
                self.exchanges += 1
                return
        self._from_fast()
        try:
            self._take_reference(y, check)
        finally:
            if self._fast is not None:  # the C cycle goes on from what the reference saw
                state = self._state
                for i, joint in enumerate(self.joints):
                    state[2 * i], state[2 * i + 1] = joint.statusword, joint.position_raw

    def compile(self, u: Any, y: Any) -> None:
        """Build the running cycle in C for the commands ``u`` and readings ``y`` the device will pass
        every cycle, before T0: built at the first enabled cycle instead, it takes that cycle long (the
        build's source check reads and checksums the C files: tens of ms under emulation)."""
        self._last_u = u
        self._compiled(y)

    def _compiled(self, y: Any) -> Any:
        """The running cycle in C on these vectors and buffers (None where the Python reference runs)."""
        from rtloop.io.compiled import refused

        self._tried = (self._last_u, y)  # tried once per pair: no import or source check each cycle
        compiled, u = self._devio, self._last_u
        self._fast = None
        if compiled is None or u is None or not isinstance(self.out_buffer, bytearray) or \
                not isinstance(self.in_buffer, bytearray):
            return None
        plan = np.full((len(self.joints), 16), -1, dtype=np.int64)
        for row, joint in zip(plan, self.joints, strict=True):
            rx, tx = joint.config.rx.offsets, joint.config.tx.offsets
            for column, (offsets, index) in enumerate(
                    ((rx, cia402.CONTROLWORD), (rx, cia402.MODES_OF_OPERATION), (rx, cia402.TARGET_POSITION),
                     (rx, cia402.TARGET_VELOCITY), (rx, cia402.TARGET_TORQUE), (tx, cia402.STATUSWORD),
                     (tx, cia402.MODES_DISPLAY), (tx, cia402.POSITION_ACTUAL), (tx, cia402.VELOCITY_ACTUAL),
                     (tx, cia402.TORQUE_ACTUAL), (tx, cia402.ERROR_CODE))):
                if index in offsets:
                    row[column] = (joint.out_at if offsets is rx else joint.in_at) + offsets[index]
            row[11:16] = (joint.u_position, joint.u_velocity, joint.u_torque, joint.u_mode, joint.y_at)
        scale = np.array([[j.rad_per_count, j.torque_per_permille] for j in self.joints], dtype=np.float64)
        self._modes = np.array([j.mode for j in self.joints], dtype=np.int64)
        self._state = np.zeros(2 * len(self.joints), dtype=np.int64)
        try:
            fast = compiled.DriveRun(self.out_buffer, self.in_buffer, u, y, plan, scale, self._modes, self._state,
                                     np.array(_STATES, dtype=np.int64))
        except (TypeError, ValueError, BufferError) as error:
            refused("a drive device's cycle", error)
            return None
        if self._link is not None:
            fast.link(*self._link)
        self._fast, self._fast_u, self._fast_y = fast, u, y
        return fast

    def _from_fast(self) -> None:
        """The joints' last statusword and position as the C cycle saw them (before the reference runs)."""
        if self._fast_used:
            self._fast_used = False
            state = self._state
            for i, joint in enumerate(self.joints):
                joint.statusword, joint.position_raw = int(state[2 * i]), int(state[2 * i + 1])

    def _take_reference(self, y: Any, check: bool) -> None:
        y = self._y.of(y)
        all_enabled = True
        table = _STATES
        buffer = self.in_buffer
        for joint in self.joints:
            values = joint.unpack(buffer, joint.in_at)
            statusword = joint.statusword = values[joint.tx_status]
            joint.position_raw = values[joint.tx_position]
            state = table[statusword & 0x6F]
            at = joint.y_at
            y[at] = joint.position_raw * joint.rad_per_count
            at += 1
            if joint.tx_velocity >= 0:
                y[at] = values[joint.tx_velocity] * joint.rad_per_count
                at += 1
            if joint.tx_torque >= 0:
                y[at] = values[joint.tx_torque] * joint.torque_per_permille
                at += 1
            y[at] = 1.0 if state == _ENABLED else 0.0
            y[at + 1] = 1.0 if statusword & _FAULT else 0.0
            y[at + 2] = 1.0 if statusword & _WARNING else 0.0
            y[at + 3] = 1.0 if statusword & _TARGET_REACHED else 0.0
            y[at + 4] = 1.0 if statusword & _FOLLOWING_ERROR and joint.mode == 8 else 0.0
            y[at + 5] = 1.0 if state == _QUICK_STOP else 0.0
            at += 6
            if joint.tx_error >= 0:
                y[at] = values[joint.tx_error]
                at += 1
            if joint.tx_mode >= 0:
                shown = values[joint.tx_mode]
                y[at] = shown
                if check and shown != joint.mode and self.exchanges - joint.mode_asked_at > MODE_LIMIT:
                    raise self._fault(joint, f"the drive shows mode {shown} (0x6061), not the "
                                      f"{cia402.MODE_NAMES.get(joint.mode, joint.mode)} it was asked for "
                                      f"{self.exchanges - joint.mode_asked_at} exchanges ago: it does not support it")
            if state != _ENABLED:
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
