"""An emulated EtherCAT slave controller (ESC): a register file that answers EtherCAT datagrams.

Each :class:`EmulatedSlave` holds 64 KiB of ESC memory (registers below 0x1000, process data
RAM above), its SII EEPROM (served through registers 0x0502-0x050F), its FMMUs (0x0600) and
sync managers (0x0800), its AL state machine (control 0x0120, status 0x0130, status code
0x0134) and the sync manager watchdog (0x0400, 0x0420) that drops it from OP to SAFE-OP when the
master stops writing its outputs, and unless built without, a distributed clocks unit
(``io/drives/esc_dc.py``: 0x0900-0x09AF; ESC feature bit 2 and the SII's DC category say it has
one). A CiA 402 :class:`~rtloop.io.drives.drive_model.DriveModel`
stands behind its process data.

:class:`Segment` is a line of slaves on one port: :meth:`Segment.process` passes an EtherCAT
frame through them in order, as the wire does (position addresses counted up on the way, every
slave ORing or copying its part, the working counters added), in place. It knows nothing of
sockets: ``io/drives/emulator.py`` puts it on a veth end; the tests call it directly.

The process-data path (a frame of LRD/LWR/LRW datagrams: the master's cycle) has a compiled twin,
``io/devio_c/esc_frame.c``, used when every slave's drive is the compiled
:func:`~rtloop.io.drives.drive_model.emulated_drive`: six drives answered in microseconds rather
than half a millisecond, so a master at 4 kHz measures itself, not the emulator. Every other frame
(registers, the SII, the AL state machine) is this module's. Both work on the same ESC memory and
the same counters (:class:`EmulatedSlave`'s ``dropped``, ``outputs_written``, ...), so either may
serve any frame; ``tests/test_drive_esc_compiled.py`` checks that they answer alike, bit for bit.
"""

from __future__ import annotations

import struct
import time
from array import array
from collections.abc import Callable
from typing import Any

from rtloop.io import compiled
from rtloop.io.drives import cia402
from rtloop.io.drives.drive_model import DriveModel
from rtloop.io.drives.esc_dc import DC_END, DC_FIRST, REG_DC_SYSTEM_TIME, DcUnit
from rtloop.io.drives.pdo import OBJECTS, PdoLayout
from rtloop.io.drives.sii import Identity, build_sii

__all__ = ["AL_STATES", "EmulatedSlave", "Segment"]

APRD, APWR, APRW, FPRD, FPWR, FPRW, BRD, BWR, BRW, LRD, LWR, LRW, ARMW, FRMW = range(1, 15)
_POSITION = (APRD, APWR, APRW, ARMW)
_FIXED = (FPRD, FPWR, FPRW, FRMW)
_BROADCAST = (BRD, BWR, BRW)
_LOGICAL = (LRD, LWR, LRW)
_READS = (APRD, FPRD, BRD)
_WRITES = (APWR, FPWR, BWR)

AL_INIT, AL_PREOP, AL_BOOT, AL_SAFEOP, AL_OP = 1, 2, 3, 4, 8
AL_ERROR = 0x10
AL_STATES = {AL_INIT: "INIT", AL_PREOP: "PRE-OP", AL_BOOT: "BOOT", AL_SAFEOP: "SAFE-OP", AL_OP: "OP"}
AL_CODE_INVALID_CHANGE = 0x0011
AL_CODE_WATCHDOG = 0x001B
AL_CODE_INVALID_OUTPUTS = 0x001D
AL_CODE_INVALID_INPUTS = 0x001E

REG_STATION, REG_ALIAS = 0x0010, 0x0012
REG_DL_STATUS = 0x0110
REG_AL_CONTROL, REG_AL_STATUS, REG_AL_CODE = 0x0120, 0x0130, 0x0134
REG_WD_DIVIDER, REG_WD_PDI, REG_WD_SM = 0x0400, 0x0410, 0x0420
REG_EEP_CONFIG, REG_EEP_CONTROL, REG_EEP_ADDRESS, REG_EEP_DATA = 0x0500, 0x0502, 0x0504, 0x0508
REG_FMMU, REG_SM = 0x0600, 0x0800
EEP_READ_8_BYTES = 0x0040
OUTPUTS_AT, INPUTS_AT = 0x1000, 0x1200
MEMORY_BYTES = 0x10000

# a slave's counters, shared with the compiled path (esc_frame.c's C_* in this order)
_DROPPED, _OUTPUTS_WRITTEN, _LAST_OUTPUTS_NS, _EXCHANGES_IN_OP, _EXCHANGES_ENABLED, _FIRST_CONTROLWORD, _HAS_DC, \
    _LOCAL_START_NS = range(8)
_RX_OBJECTS = (cia402.CONTROLWORD, cia402.MODES_OF_OPERATION, cia402.TARGET_POSITION, cia402.TARGET_VELOCITY,
               cia402.TARGET_TORQUE)
_TX_KINDS = {cia402.STATUSWORD: 0, cia402.MODES_DISPLAY: 1, cia402.POSITION_ACTUAL: 2, cia402.VELOCITY_ACTUAL: 3,
             cia402.TORQUE_ACTUAL: 4, cia402.FOLLOWING_ERROR_ACTUAL: 5, cia402.ERROR_CODE: 6}


def _state_name(code: int) -> str:
    return AL_STATES.get(code & 0x0F, f"0x{code & 0x0F:X}") + (" +ERROR" if code & AL_ERROR else "")


class EmulatedSlave:
    """One slave: ESC memory, SII, AL state machine, watchdog, and a drive behind the process data."""

    def __init__(self, position: int, identity: Identity, rx: PdoLayout, tx: PdoLayout, drive: DriveModel,
                 name: str = "rtloop emulated CiA 402 drive", log: Callable[[str], None] | None = None,
                 clock: Callable[[], int] = time.monotonic_ns, dc: bool = True) -> None:
        self.position = position
        self.identity = identity
        self.rx, self.tx = rx, tx
        self.drive = drive
        self.memory = bytearray(MEMORY_BYTES)
        self.counters = array("q", [0, 0, 0, 0, 0, -1, 0, 0])
        """dropped, outputs_written, last_outputs_ns, exchanges_in_op, exchanges_enabled, the
        controlword of the first exchange in OP that the compiled path leaves to the log (-1: none),
        whether it has a DC unit and that unit's local start."""
        self.sii = build_sii(identity, name, rx.entries(), tx.entries(), OUTPUTS_AT, INPUTS_AT, dc=dc)
        self.log = log or (lambda text: None)
        self.clock = clock
        self.dc = DcUnit(self.memory, position, position, clock, self.log) if dc else None
        m = self.memory
        m[0x0000] = 0x11  # ESC type
        m[0x0001] = 0x01
        struct.pack_into("<H", m, 0x0002, 0x0001)  # build
        m[0x0004], m[0x0005] = 8, 8  # FMMUs, sync managers
        m[0x0006] = 8  # RAM KiB
        m[0x0007] = 0x0F  # ports 0 and 1: MII
        struct.pack_into("<H", m, 0x0008, 0x000C if dc else 0x0000)  # features: distributed clocks, 64 bits
        struct.pack_into("<H", m, REG_AL_STATUS, AL_INIT)
        struct.pack_into("<H", m, REG_EEP_CONTROL, EEP_READ_8_BYTES)
        struct.pack_into("<H", m, REG_WD_DIVIDER, 2498)  # 100 µs units
        struct.pack_into("<H", m, REG_WD_PDI, 1000)
        struct.pack_into("<H", m, REG_WD_SM, 1000)  # 100 ms
        self._write_tx()

    # --- state (the counters the compiled path shares) --------------------------------------------
    @property
    def dropped(self) -> bool:
        """Fault injection: a slave that dropped out (a broken cable, power lost) answers nothing."""
        return bool(self.counters[_DROPPED])

    @dropped.setter
    def dropped(self, value: bool) -> None:
        self.counters[_DROPPED] = int(value)

    @property
    def dc(self) -> DcUnit | None:
        """The distributed clocks unit (None: a slave without DC, free-running on the frames)."""
        return self._dc

    @dc.setter
    def dc(self, unit: DcUnit | None) -> None:
        self._dc = unit
        self.counters[_HAS_DC] = int(unit is not None)
        self.counters[_LOCAL_START_NS] = unit.local_start_ns if unit is not None else 0

    @property
    def outputs_written(self) -> bool:
        return bool(self.counters[_OUTPUTS_WRITTEN])

    @outputs_written.setter
    def outputs_written(self, value: bool) -> None:
        self.counters[_OUTPUTS_WRITTEN] = int(value)

    @property
    def last_outputs_ns(self) -> int:
        return self.counters[_LAST_OUTPUTS_NS]

    @last_outputs_ns.setter
    def last_outputs_ns(self, value: int) -> None:
        self.counters[_LAST_OUTPUTS_NS] = value

    @property
    def exchanges_in_op(self) -> int:
        return self.counters[_EXCHANGES_IN_OP]

    @exchanges_in_op.setter
    def exchanges_in_op(self, value: int) -> None:
        self.counters[_EXCHANGES_IN_OP] = value

    @property
    def exchanges_enabled(self) -> int:
        """Process-data exchanges with the drive in operation enabled (when injected faults fall due)."""
        return self.counters[_EXCHANGES_ENABLED]

    @exchanges_enabled.setter
    def exchanges_enabled(self, value: int) -> None:
        self.counters[_EXCHANGES_ENABLED] = value

    @property
    def al_status(self) -> int:
        return int(struct.unpack_from("<H", self.memory, REG_AL_STATUS)[0])

    def set_link(self, last: bool) -> None:
        """DL status: port 0 carries the frames in; port 1 passes them on unless this is the last slave."""
        status = 0x0200 | (0 if last else 0x0800) | (0x0400 if last else 0)  # port 1 loop closed when last
        struct.pack_into("<H", self.memory, REG_DL_STATUS, status | 0x0001)

    def _set_al(self, state: int, code: int = 0, why: str = "") -> None:
        old = self.al_status
        struct.pack_into("<H", self.memory, REG_AL_STATUS, state)
        struct.pack_into("<H", self.memory, REG_AL_CODE, code)
        if old != state:
            extra = f" (AL status code 0x{code:04X})" if code else ""
            self.log(f"slave {self.position}: AL {_state_name(old)} -> {_state_name(state)}{why}{extra}")
            if old & 0x0F == AL_OP and state & 0x0F != AL_OP:
                self.log(f"slave {self.position}: left OP{why}")
                self.drive.outputs_lost()
                self._take_drive_events()
            if state & 0x0F == AL_OP:
                self.last_outputs_ns = self.clock()
                self.exchanges_in_op = 0

    def watchdog_ns(self) -> int:
        divider, = struct.unpack_from("<H", self.memory, REG_WD_DIVIDER)
        time_units, = struct.unpack_from("<H", self.memory, REG_WD_SM)
        return int((divider + 2) * 40 * time_units)

    def tick(self, now_ns: int) -> None:
        """The SM watchdog: in OP, outputs not written for longer than its time → SAFE-OP with an error;
        the DC unit's SYNC0."""
        if self.dc is not None:
            self.dc.tick()
        if self.al_status & 0x0F == AL_OP and not self.dropped:
            limit = self.watchdog_ns()
            if limit and now_ns - self.last_outputs_ns > limit:
                self._set_al(AL_SAFEOP | AL_ERROR, AL_CODE_WATCHDOG,
                             f" (SM watchdog: no process data for {(now_ns - self.last_outputs_ns) / 1e6:.0f} ms)")

    def _request_state(self, control: int) -> None:
        status = self.al_status
        current, error = status & 0x0F, status & AL_ERROR
        wanted, ack = control & 0x0F, control & AL_ERROR
        if error and not ack and wanted != AL_INIT:
            return  # an error must be acknowledged before the slave moves on
        if wanted == current:
            if error and ack:
                self._set_al(current, 0, " (error acknowledged)")
            return
        allowed = {AL_INIT: (AL_INIT, AL_PREOP, AL_SAFEOP, AL_OP), AL_PREOP: (AL_INIT, AL_PREOP, AL_SAFEOP, AL_OP),
                   AL_SAFEOP: (AL_PREOP, AL_SAFEOP, AL_OP), AL_OP: (AL_SAFEOP, AL_OP)}
        if wanted not in allowed or current not in allowed.get(wanted, ()):
            self._set_al(current | AL_ERROR, AL_CODE_INVALID_CHANGE, f" (refused {_state_name(wanted)})")
            return
        if wanted == AL_SAFEOP and current == AL_PREOP:
            problem = self._sync_manager_problem()
            if problem:
                self._set_al(current | AL_ERROR, problem[0], f" (refused SAFE-OP: {problem[1]})")
                return
        self._set_al(wanted, 0, " (requested)")

    def _sync_manager_problem(self) -> tuple[int, str] | None:
        for number, (start, size, code, what) in enumerate(((OUTPUTS_AT, self.rx.size, AL_CODE_INVALID_OUTPUTS,
                                                            "outputs"),
                                                           (INPUTS_AT, self.tx.size, AL_CODE_INVALID_INPUTS,
                                                            "inputs"))):
            at = REG_SM + 8 * number
            sm_start, sm_length, _control, _status, activate = struct.unpack_from("<HHBBB", self.memory, at)
            if size and (sm_start != start or sm_length != size or not activate & 1):
                return code, (f"SM{number} ({what}) set to start 0x{sm_start:04X}, length {sm_length}, "
                              f"enable {activate & 1}; it must be 0x{start:04X}, {size} bytes, enabled")
        return None

    # --- register access --------------------------------------------------------------------------
    def read(self, address: int, data: memoryview, mode: str) -> None:
        """Registers into ``data``: ``copy`` (a read) or ``or`` (a broadcast read)."""
        end = min(address + len(data), 0x10000)
        if self.dc is not None and address < DC_END and end > DC_FIRST:
            self.dc.refresh()
        if mode == "or":
            for i in range(end - address):
                data[i] |= self.memory[address + i]
        else:
            data[:end - address] = self.memory[address:end]

    def write(self, address: int, data: memoryview) -> None:
        end = min(address + len(data), 0x10000)
        for start, stop in ((0x0000, 0x0010), (REG_AL_STATUS, REG_AL_STATUS + 6), (REG_DL_STATUS, REG_DL_STATUS + 2)):
            if address < stop and end > start:  # read-only registers keep their value
                saved = bytes(self.memory[start:stop])
                self.memory[address:end] = data[:end - address]
                self.memory[start:stop] = saved
                break
        else:
            self.memory[address:end] = data[:end - address]
        if self.dc is not None and address < DC_END and end > DC_FIRST:
            self.dc.written(address, end)
        if address <= REG_AL_CONTROL < end:
            control, = struct.unpack_from("<H", self.memory, REG_AL_CONTROL)
            self._request_state(control)
        if address <= REG_EEP_CONTROL < end:
            self._eeprom_command()
        if address < OUTPUTS_AT + self.rx.size and end > OUTPUTS_AT:
            self.outputs_written = True

    def _eeprom_command(self) -> None:
        control, = struct.unpack_from("<H", self.memory, REG_EEP_CONTROL)
        command = (control >> 8) & 0x07
        status = EEP_READ_8_BYTES
        if command == 1:  # read 8 bytes from the word address
            word, = struct.unpack_from("<I", self.memory, REG_EEP_ADDRESS)
            chunk = self.sii[word * 2:word * 2 + 8]
            self.memory[REG_EEP_DATA:REG_EEP_DATA + 8] = chunk + b"\xff" * (8 - len(chunk))
        elif command:
            status |= 0x2000  # no acknowledge: writing and reloading are not emulated
        struct.pack_into("<H", self.memory, REG_EEP_CONTROL, status)

    # --- logical addressing through the FMMUs -----------------------------------------------------
    def logical(self, command: int, address: int, data: memoryview) -> int:
        """Copy between the frame and memory through every active FMMU; the working counter's share."""
        read = wrote = False
        length = len(data)
        for number in range(8):
            at = REG_FMMU + 16 * number
            start, size, _sb, _eb, physical, _pb, kind, active = struct.unpack_from("<IHBBHBBB", self.memory, at)
            if not active & 1 or not size:
                continue
            low, high = max(start, address), min(start + size, address + length)
            if low >= high:
                continue
            frame_at, memory_at = low - address, physical + (low - start)
            count = min(high - low, MEMORY_BYTES - memory_at)  # not past the memory's end
            if kind & 1 and command in (LRD, LRW):  # the master reads: inputs into the frame
                data[frame_at:frame_at + count] = self.memory[memory_at:memory_at + count]
                read = True
            if kind & 2 and command in (LWR, LRW):  # the master writes: outputs into memory
                self.memory[memory_at:memory_at + count] = data[frame_at:frame_at + count]
                if memory_at < OUTPUTS_AT + self.rx.size and memory_at + count > OUTPUTS_AT:
                    self.outputs_written = True
                # outputs count in the working counter in OP only: a master sees a slave that left OP
                wrote = self.al_status & 0x0F == AL_OP
        if command == LRW:
            return (1 if read else 0) + (2 if wrote else 0)
        return 1 if read or wrote else 0

    # --- the drive behind the process data ------------------------------------------------------
    def application(self, now_ns: int) -> None:
        """After a frame wrote the outputs: the drive takes them and computes its next inputs."""
        self.outputs_written = False
        in_op = self.al_status & 0x0F == AL_OP
        if in_op:
            self.last_outputs_ns = now_ns
            self.exchanges_in_op += 1
            if self.drive.state == cia402.Cia402State.OPERATION_ENABLED:
                self.exchanges_enabled += 1
        values = self.rx.struct.unpack_from(self.memory, OUTPUTS_AT)
        rx = self.rx.position
        drive = self.drive

        def get(index: int, default: int) -> int:
            return int(values[rx[index]]) if index in rx else default

        if in_op and self.exchanges_in_op == 1:  # when the master's outputs begin to count, and what they say
            self._say_first_exchange(get(cia402.CONTROLWORD, 0))
        drive.exchange(get(cia402.CONTROLWORD, 0), get(cia402.MODES_OF_OPERATION, drive.mode),
                       get(cia402.TARGET_POSITION, 0), get(cia402.TARGET_VELOCITY, 0), get(cia402.TARGET_TORQUE, 0),
                       outputs_valid=in_op)
        self._write_tx()
        self._take_drive_events()

    def _say_first_exchange(self, controlword: int) -> None:
        self.log(f"slave {self.position}: first process data in OP (controlword 0x{controlword:04X})")

    def take_compiled_news(self) -> None:
        """Log what the compiled path left to say: the first exchange in OP, the drive's events."""
        controlword = self.counters[_FIRST_CONTROLWORD]
        if controlword >= 0:
            self.counters[_FIRST_CONTROLWORD] = -1
            self._say_first_exchange(controlword)
        self._take_drive_events()

    def compiled_layout(self) -> list[int]:
        """Where the drive's objects are in the outputs and inputs, for the compiled path: the rx size,
        the offsets of controlword, mode, target position, velocity and torque (-1: not mapped), then
        each tx entry's kind and offset, in order."""
        layout = [self.rx.size, *(self.rx.offsets.get(index, -1) for index in _RX_OBJECTS)]
        at = 0
        for index in self.tx.objects:
            layout += [_TX_KINDS[index], at]
            at += OBJECTS[index].bits // 8
        return layout

    def _take_drive_events(self) -> None:
        for event in self.drive.events:
            self.log(f"slave {self.position}: drive: {event}")
        self.drive.events.clear()

    def _write_tx(self) -> None:
        self.tx.struct.pack_into(self.memory, INPUTS_AT, *tx_values(self.drive, self.tx))


def tx_values(drive: DriveModel, tx: PdoLayout) -> list[int]:
    """The drive's objects in the order of its TxPDO mapping."""
    values = {cia402.STATUSWORD: drive.statusword, cia402.MODES_DISPLAY: drive.mode_display,
              cia402.POSITION_ACTUAL: drive.position, cia402.VELOCITY_ACTUAL: drive.velocity,
              cia402.TORQUE_ACTUAL: drive.torque, cia402.FOLLOWING_ERROR_ACTUAL: drive.following_error,
              cia402.ERROR_CODE: drive.error_code}
    return [values[index] for index in tx.objects]


class Segment:
    """Slaves in a line: a frame passes each in order and comes back."""

    def __init__(self, slaves: list[EmulatedSlave], clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.slaves = slaves
        self.clock = clock
        for slave in slaves:
            slave.set_link(last=slave is slaves[-1])
            if slave.dc is not None:
                slave.dc.slaves = len(slaves)
        self._compiled = self._compiled_path()
        self._sync0_waiting = self._waiting_for_sync0()

    @property
    def compiled(self) -> bool:
        """Does the compiled path serve the process data (every drive compiled, ``_devio`` built)?"""
        return self._compiled is not None

    def _compiled_path(self) -> Any:
        module = compiled.devio()
        if module is None or not self.slaves or not all(isinstance(slave.drive, module.EmulatedDrive)
                                                        for slave in self.slaves):
            return None
        try:
            return module.EscFrames([slave.memory for slave in self.slaves],
                                    [slave.counters for slave in self.slaves], [slave.drive for slave in self.slaves],
                                    [slave.compiled_layout() for slave in self.slaves],
                                    [slave.clock for slave in self.slaves], [slave.read for slave in self.slaves],
                                    self.clock)
        except ValueError:  # a mapping the compiled path does not take (over 16 inputs): Python serves it
            return None

    def tick(self, now_ns: int) -> None:
        """Every slave's :meth:`EmulatedSlave.tick` (SM watchdog, SYNC0's first pulse); the watchdogs are
        checked in C first where they can be."""
        if self._compiled is None or self._sync0_waiting or self._compiled.expired(now_ns):
            for slave in self.slaves:
                slave.tick(now_ns)
            self._sync0_waiting = self._waiting_for_sync0()

    def _waiting_for_sync0(self) -> bool:
        """Is a DC unit's first SYNC0 pulse still to be logged (by its tick)? Only a register write
        (the Python path) or a tick changes that."""
        return any(s.dc is not None and s.dc.sync0_active and not s.dc.sync0_pulsed for s in self.slaves)

    def process(self, frame: bytearray | memoryview, offset: int = 14) -> bool:
        """Pass the EtherCAT frame (Ethernet header at 0, EtherCAT header at ``offset``) through every
        slave, in place. False when it carries no EtherCAT datagrams."""
        if self._compiled is not None:
            done = self._compiled.process(frame, offset)
            if done == 2:
                for slave in self.slaves:
                    slave.take_compiled_news()
            if done >= 0:
                return bool(done)
            self._sync0_waiting = True  # the Python path may start SYNC0: the next tick looks
        view = memoryview(frame)
        header, = struct.unpack_from("<H", frame, offset)
        if header >> 12 != 1:
            return False
        total = header & 0x07FF
        at, end = offset + 2, offset + 2 + total
        outputs = False
        while at + 12 <= end:
            command, _index, adp, ado, length_field = struct.unpack_from("<BBHHH", frame, at)
            length = length_field & 0x07FF
            data = view[at + 10:at + 10 + length]
            wkc, = struct.unpack_from("<H", frame, at + 10 + length)
            if command in _LOGICAL:
                logical_address, = struct.unpack_from("<I", frame, at + 2)
                for slave in self.slaves:
                    if not slave.dropped:
                        wkc += slave.logical(command, logical_address, data)
                outputs = outputs or command in (LWR, LRW)
            else:
                for slave in self.slaves:
                    if slave.dropped:
                        continue
                    wkc, adp = self._register_datagram(slave, command, adp, ado, data, wkc)
                struct.pack_into("<H", frame, at + 2, adp)
            struct.pack_into("<H", frame, at + 10 + length, wkc)
            at += 12 + length
            if not length_field & 0x8000:
                break
        now = self.clock()
        if outputs:
            for slave in self.slaves:
                if slave.outputs_written and not slave.dropped:
                    slave.application(now)
        view.release()
        return True

    @staticmethod
    def _register_datagram(slave: EmulatedSlave, command: int, adp: int, ado: int, data: memoryview,
                           wkc: int) -> tuple[int, int]:
        if command in _POSITION:
            addressed = adp == 0
            adp = (adp + 1) & 0xFFFF
        elif command in _FIXED:
            station, = struct.unpack_from("<H", slave.memory, REG_STATION)
            addressed = adp == station
        elif command in _BROADCAST:
            addressed = True
            adp = (adp + 1) & 0xFFFF
        else:
            return wkc, adp
        if not addressed:
            # the others write what the reference slave read (a slave without DC has no system time to set)
            if command in (ARMW, FRMW) and (slave.dc is not None or ado != REG_DC_SYSTEM_TIME):
                slave.write(ado, data)
                wkc += 1
            return wkc, adp
        if command in (ARMW, FRMW) and slave.dc is None and ado == REG_DC_SYSTEM_TIME:
            return wkc, adp  # no system time to read: the reference clock's time does not go out
        if command in (BRD,):
            slave.read(ado, data, "or")
            wkc += 1
        elif command in _READS or command in (ARMW, FRMW):
            slave.read(ado, data, "copy")
            wkc += 1
        elif command in _WRITES:
            slave.write(ado, data)
            wkc += 1
        elif command in (APRW, FPRW, BRW):
            written = bytes(data)
            slave.read(ado, data, "copy")
            slave.write(ado, memoryview(written))
            wkc += 3
        return wkc, adp
