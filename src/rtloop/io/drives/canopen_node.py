"""An emulated CANopen CiA 402 drive node: NMT, SDO (expedited and segmented), SYNC-driven PDOs, heartbeat, EMCY,
with the drive model (``io/drives/drive_model.py``) behind its PDOs.

    rtloop io emulate canopen --interface vcan0 --node 3 --log node.log
    rtloop io emulate canopen --app examples/canopen_axis/canopen_axis.toml --log node.log

:class:`CanopenNode` is the node's logic, frame in → frames out, with no socket (the host's tests
drive it in process); :func:`serve` puts it on a SocketCAN interface. The node keeps an object
dictionary of the objects a master configures (identity 0x1018, heartbeat producer 0x1017 and
consumer 0x1016, cycle period 0x1006, PDO communication and mapping 0x1400-0x1A03) and learns its
PDO mapping from the master's SDO writes. At each SYNC while operational it sends its TPDOs with
the values the drive holds, then steps the drive once with the RPDO values last received: the
order of the EtherCAT twin (``EthercatTwin``), so a run against this node equals ``rtloop simulate`` bit for bit.

Its safe reactions: NMT stop or pre-operational, no SYNC for ``sync_timeout_s`` while the drive
is enabled, or the master's heartbeat missing for the consumer time of 0x1016 (the master's task
killed): the drive quick-stops by itself (the last also sends EMCY 0x8130 and goes pre-operational). A drive fault
sends an EMCY (its error code, error register 0x01). The log says every NMT and drive state change.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import struct
import sys
import time
from collections.abc import Callable
from typing import TextIO

from rtloop.io.drives import cia402
from rtloop.io.drives.canopen_sdo import SdoServer
from rtloop.io.drives.canopen_wire import (
    HEARTBEAT_STATES,
    NMT_PRE_OPERATIONAL,
    NMT_RESET_COMMUNICATION,
    NMT_RESET_NODE,
    NMT_START,
    NMT_STOP,
    SYNC_ID,
    WIRE,
    emcy_id,
    heartbeat_id,
    pdo_chunks,
    sdo_answer_id,
    sdo_request_id,
)
from rtloop.io.drives.drive_model import DriveModel, DriveParameters
from rtloop.io.drives.pdo import DEFAULT_RXPDO, DEFAULT_TXPDO, OBJECTS, PdoLayout
from rtloop.io.drives.sii import Identity

__all__ = ["CanopenNode", "add_arguments", "serve"]

Frame = tuple[int, bytes]
BOOT, STOPPED, OPERATIONAL, PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F
DEFAULT_IDENTITY = Identity(0xA7E, 0x402402, 0x10000)
ABORT_NO_OBJECT, ABORT_WRITE_ONLY_IN_PREOP = 0x06020000, 0x08000022
POLL_S = 0.01
"""How long the node waits for a frame before it looks at its heartbeat and SYNC watch again: often
enough for both, seldom enough that a node at SCHED_FIFO leaves the CPU to others (under emulation a
1 ms poll kept a whole guest CPU busy)."""


class CanopenNode:
    """One node's logic. ``receive`` takes a frame and returns the frames to send; ``tick`` (called
    often) sends the heartbeat and watches SYNC; ``log`` is told every state change."""

    def __init__(self, node: int, parameters: DriveParameters | None = None, identity: Identity = DEFAULT_IDENTITY,
                 log: Callable[[str], None] = lambda text: None, sync_timeout_s: float = 0.1) -> None:
        self.node = node
        self.parameters = parameters or DriveParameters()
        self.identity = identity
        self.log = log
        self.sync_timeout_s = sync_timeout_s
        self.od: dict[tuple[int, int], int] = {}
        self.od_bytes: dict[tuple[int, int], bytes] = {}  # strings and domains: any length, segmented beyond 4
        self.sdo_server = SdoServer()
        self.drive = DriveModel(self.parameters)
        self.nmt = BOOT
        self.pending_fault = 0
        self.inject_at_sync = -1
        self.syncs_enabled = 0
        """SYNCs with the drive in operation enabled (where ``--inject fault@N`` counts)."""
        self._reset_communication(0.0)

    # --- the object dictionary ------------------------------------------------------------------
    def _reset_communication(self, now_s: float) -> None:
        od = self.od
        od.clear()
        od[(0x1000, 0)] = 0x00020192  # device type: CiA 402 drive
        od[(0x1006, 0)] = 0  # communication cycle period, µs (0: not watched)
        od[(0x1016, 0)] = 1
        od[(0x1016, 1)] = 0  # heartbeat consumer: the watched node << 16 | its time, ms (0: not watched)
        od[(0x1017, 0)] = 0  # heartbeat producer time, ms (0: none)
        self.od_bytes = {(0x1008, 0): b"rtloop emulated CiA 402 drive",  # manufacturer device name
                         (0x2100, 0): b""}  # manufacturer-specific: the axis's label (a value of any length)
        od[(0x1018, 0)] = 3
        od[(0x1018, 1)], od[(0x1018, 2)], od[(0x1018, 3)] = (self.identity.vendor, self.identity.product,
                                                             self.identity.revision)
        od[(0x6502, 0)] = sum(1 << (mode - 1) for mode in self.parameters.modes)  # supported drive modes
        for objects, comm, mapping, cob, base in ((DEFAULT_RXPDO, 0x1400, 0x1600, 0x200, 0),
                                                  (DEFAULT_TXPDO, 0x1800, 0x1A00, 0x180, 0)):
            chunks = pdo_chunks(PdoLayout(objects))
            for number in range(4):
                od[(comm + number, 1)] = cob + 0x100 * number + self.node | (0 if number < len(chunks) else 1 << 31)
                od[(comm + number, 2)] = 1 + base
                entries = chunks[number][2] if number < len(chunks) else ()
                od[(mapping + number, 0)] = len(entries)
                for sub in range(1, 9):
                    od[(mapping + number, sub)] = (entries[sub - 1] << 16 | OBJECTS[entries[sub - 1]].bits
                                                   if sub <= len(entries) else 0)
        self.rx_values = {index: 0 for index in DEFAULT_RXPDO}
        self.rx_values[cia402.MODES_OF_OPERATION] = self.drive.mode
        self.last_heartbeat_s = now_s
        self.last_sync_s = now_s
        self.consumed_s = -1.0  # the watched node's last heartbeat (-1: none yet, the watch not armed)

    def _pdos(self, comm: int, mapping: int) -> list[tuple[int, tuple[int, ...]]]:
        """The valid PDOs: (COB-ID, objects) per PDO."""
        pdos = []
        for number in range(4):
            cob_id = self.od[(comm + number, 1)]
            if cob_id & 1 << 31:
                continue
            count = self.od[(mapping + number, 0)]
            pdos.append((cob_id & 0x7FF, tuple(self.od[(mapping + number, sub)] >> 16 for sub in range(1, count + 1))))
        return pdos

    # --- frames in, frames out ----------------------------------------------------------------------
    def boot(self, now_s: float) -> list[Frame]:
        """Power on: the boot-up message, then pre-operational."""
        self._set_nmt(PRE_OPERATIONAL, "boot-up")
        self.last_heartbeat_s = now_s
        return [(heartbeat_id(self.node), bytes([BOOT]))]

    def _set_nmt(self, state: int, why: str) -> None:
        if state != self.nmt:
            self.nmt = state
            self.log(f"node {self.node}: NMT {HEARTBEAT_STATES[state]} ({why})")

    def receive(self, can_id: int, data: bytes, now_s: float) -> list[Frame]:
        if can_id == 0x000 and len(data) >= 2 and data[1] in (0, self.node):
            return self._nmt_command(data[0], now_s)
        if can_id == sdo_request_id(self.node) and len(data) == 8 and self.nmt in (PRE_OPERATIONAL, OPERATIONAL):
            if data[0] == 0x80:  # the client aborts its transfer: no answer
                self.sdo_server = SdoServer()
                return []
            return [(sdo_answer_id(self.node), self._sdo(data))]
        if can_id == heartbeat_id(self.od[(0x1016, 1)] >> 16 & 0x7F) and self.od[(0x1016, 1)] & 0xFFFF:
            self.consumed_s = now_s  # CiA 301: the consumer watches from the first heartbeat it receives
            return []
        if can_id == SYNC_ID and self.nmt == OPERATIONAL:
            self.last_sync_s = now_s
            return self._sync()
        if self.nmt == OPERATIONAL:
            for cob_id, objects in self._pdos(0x1400, 0x1600):
                if can_id == cob_id:
                    values = struct.unpack_from("<" + "".join(OBJECTS[i].code for i in objects), data.ljust(8, b"\0"))
                    self.rx_values.update(zip(objects, values, strict=True))
        return []

    def _nmt_command(self, command: int, now_s: float) -> list[Frame]:
        if command == NMT_START:
            self.last_sync_s = now_s
            self._set_nmt(OPERATIONAL, "NMT start")
        elif command in (NMT_STOP, NMT_PRE_OPERATIONAL):
            if self.nmt == OPERATIONAL:
                self._outputs_lost("NMT stop" if command == NMT_STOP else "NMT pre-operational")
            self._set_nmt(STOPPED if command == NMT_STOP else PRE_OPERATIONAL,
                          "NMT stop" if command == NMT_STOP else "NMT enter pre-operational")
        elif command in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
            if self.nmt == OPERATIONAL:
                self._outputs_lost("NMT reset")
            self._reset_communication(now_s)
            self.nmt = BOOT
            return self.boot(now_s)
        return []

    def _outputs_lost(self, why: str) -> None:
        """The master's PDOs no longer come: an enabled drive quick-stops on its own ramp, then is
        brought to switch on disabled once at rest (stepped here, at the drive's own cycle)."""
        drive = self.drive
        if drive.state == cia402.Cia402State.OPERATION_ENABLED:
            self.log(f"node {self.node}: {why}: quick stop")
            drive.outputs_lost()
            self._take_events()
            for _ in range(round(10.0 / drive.p.cycle_s)):  # at most 10 s of braking
                drive.exchange(cia402.CW_QUICK_STOP, drive.mode, drive.position, 0, 0)
                self._take_events()
                if drive.statusword & cia402.StatusBits.TARGET_REACHED:
                    break
            drive.exchange(cia402.CW_DISABLE_VOLTAGE, drive.mode, drive.position, 0, 0)
            self._take_events()

    def _sdo(self, data: bytes) -> bytes:
        server = self.sdo_server
        if data[0] & 0xE0 == 0x60:  # upload segment
            return server.upload_segment(data)
        if data[0] & 0xE0 == 0x00:  # download segment
            answer, value = server.download_segment(data)
            if value is not None:
                self.od_bytes[server.key] = value
                self.log(f"node {self.node}: SDO 0x{server.key[0]:04X}:{server.key[1]} written, {len(value)} bytes "
                         "(segmented)")
            return answer
        command, index, sub = struct.unpack_from("<BHB", data, 0)
        key = (index, sub)
        if key in self.od_bytes:
            if command == 0x40:
                return server.initiate_upload(index, sub, self.od_bytes[key])
            if command & 0xE3 == 0x21:  # segmented download, size indicated
                return server.initiate_download(index, sub, data)
            if command & 0xE3 == 0x23:  # expedited
                self.od_bytes[key] = bytes(data[4:8 - (command >> 2 & 3)])
                return struct.pack("<BHB4x", 0x60, index, sub)
            return struct.pack("<BHBI", 0x80, index, sub, 0x05040001)
        if key not in self.od:
            return struct.pack("<BHBI", 0x80, index, sub, ABORT_NO_OBJECT)
        if command & 0xE3 == 0x21:  # segmented download of a number: more bytes than it has
            return struct.pack("<BHBI", 0x80, index, sub, 0x06070012)
        if command == 0x40:  # upload
            return struct.pack("<BHBI", 0x43, index, sub, self.od[key] & 0xFFFFFFFF)
        if command & 0xE3 == 0x23:  # expedited download, size indicated
            if self.nmt == OPERATIONAL and 0x1400 <= index <= 0x1BFF:
                return struct.pack("<BHBI", 0x80, index, sub, ABORT_WRITE_ONLY_IN_PREOP)
            size = 4 - (command >> 2 & 3)
            self.od[key] = int.from_bytes(data[4:4 + size], "little")
            if 0x1600 <= index <= 0x1603 and sub == 0:
                self.rx_values.update({self.od[(index, s)] >> 16: 0 for s in range(1, self.od[key] + 1)})
                self.rx_values[cia402.MODES_OF_OPERATION] = self.drive.mode
            return struct.pack("<BHB4x", 0x60, index, sub)
        return struct.pack("<BHBI", 0x80, index, sub, 0x05040001)  # command specifier not valid

    def _sync(self) -> list[Frame]:
        drive = self.drive
        frames = [(cob_id, self._tpdo(objects)) for cob_id, objects in self._pdos(0x1800, 0x1A00)]
        if drive.state == cia402.Cia402State.OPERATION_ENABLED:
            self.syncs_enabled += 1
            if self.syncs_enabled == self.inject_at_sync:
                self.log(f"node {self.node}: injected drive fault at SYNC {self.syncs_enabled} (enabled)")
                drive.inject_fault()
        code_before = drive.error_code
        values = self.rx_values
        drive.exchange(values.get(cia402.CONTROLWORD, 0), values.get(cia402.MODES_OF_OPERATION, drive.mode),
                       values.get(cia402.TARGET_POSITION, 0), values.get(cia402.TARGET_VELOCITY, 0),
                       values.get(cia402.TARGET_TORQUE, 0))
        self._take_events()
        if drive.error_code and drive.error_code != code_before:
            self.log(f"node {self.node}: EMCY 0x{drive.error_code:04X}")
            frames.append((emcy_id(self.node), struct.pack("<HB5x", drive.error_code, 0x01)))
        return frames

    def _tpdo(self, objects: tuple[int, ...]) -> bytes:
        drive = self.drive
        held = {cia402.STATUSWORD: drive.statusword, cia402.MODES_DISPLAY: drive.mode_display,
                cia402.POSITION_ACTUAL: drive.position, cia402.VELOCITY_ACTUAL: drive.velocity,
                cia402.TORQUE_ACTUAL: drive.torque, cia402.FOLLOWING_ERROR_ACTUAL: drive.following_error,
                cia402.ERROR_CODE: drive.error_code}
        return struct.pack("<" + "".join(OBJECTS[i].code for i in objects), *(held.get(i, 0) for i in objects))

    def _take_events(self) -> None:
        for event in self.drive.events:
            self.log(f"node {self.node}: drive {event}")
        self.drive.events.clear()

    def tick(self, now_s: float) -> list[Frame]:
        """The heartbeat when due; the SYNC watch while operational."""
        frames: list[Frame] = []
        period_ms = self.od[(0x1017, 0)]
        if period_ms and self.nmt != BOOT and now_s - self.last_heartbeat_s >= period_ms / 1000.0:
            self.last_heartbeat_s = now_s
            frames.append((heartbeat_id(self.node), bytes([self.nmt])))
        if (self.nmt == OPERATIONAL and self.drive.state == cia402.Cia402State.OPERATION_ENABLED
                and now_s - self.last_sync_s > self.sync_timeout_s):
            self._outputs_lost(f"no SYNC for {(now_s - self.last_sync_s) * 1e3:.0f} ms (sync lost)")
        consumer = self.od[(0x1016, 1)]
        if consumer & 0xFFFF and self.consumed_s >= 0 and now_s - self.consumed_s > (consumer & 0xFFFF) / 1000.0:
            frames += self._heartbeat_lost(consumer >> 16 & 0x7F, consumer & 0xFFFF, now_s)
        return frames

    def _heartbeat_lost(self, producer: int, time_ms: int, now_s: float) -> list[Frame]:
        """The heartbeat consumer's event (CiA 301): EMCY 0x8130, and the error behaviour 0x1029's
        default, an operational node goes pre-operational: its enabled drive quick-stops, then disables."""
        silent_ms = (now_s - self.consumed_s) * 1e3
        self.consumed_s = -1.0  # one event per loss: armed again by the next heartbeat
        if self.nmt != OPERATIONAL:
            return []  # the master left operation itself (its last word was NMT): nothing to stop
        self.log(f"node {self.node}: heartbeat consumer: none from node {producer} for {silent_ms:.0f} ms "
                 f"(0x1016: {time_ms} ms): EMCY 0x8130, quick stop, then pre-operational")
        self._outputs_lost("heartbeat lost")
        self._set_nmt(PRE_OPERATIONAL, "heartbeat lost")
        return [(emcy_id(self.node), struct.pack("<HB5x", 0x8130, 0x11))]  # error register: generic, communication


# --- on a SocketCAN interface ---------------------------------------------------------------------------

def _can_fix(interface: str) -> str:
    """What to do when ``interface`` does not open as a CAN socket."""
    from rtloop.io.cansocket import can_supported

    if can_supported():
        return ("this kernel has no SocketCAN: run it on a kernel with the can and vcan modules "
                "(the PREEMPT_RT test guest has them: tools/rtkernel-vm.sh, docs/rtkernel-guest.md)")
    return (f"make a virtual bus with: sudo ip link add {interface} type vcan; sudo ip link set {interface} up "
            f"(a real bus: sudo ip link set {interface} up type can bitrate 500000)")


def serve(interface: str, node: CanopenNode, stop_after_s: float = 0.0, priority: int = 0) -> int:
    """Answer on ``interface`` until SIGTERM/SIGINT (or ``stop_after_s``), at SCHED_FIFO ``priority``
    when given (a drive must answer within the master's TPDO timeout)."""
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        sock.bind((interface,))
    except (OSError, AttributeError) as error:
        print(f"rtloop io emulate canopen: cannot open CAN interface {interface!r}: "
              f"{getattr(error, 'strerror', None) or error}: {_can_fix(interface)}", file=sys.stderr)
        return 3
    sock.settimeout(POLL_S)
    stopping = []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append(1))
    signal.signal(signal.SIGINT, lambda *_: stopping.append(1))

    def send(frames: list[Frame]) -> None:
        for can_id, data in frames:
            try:
                sock.send(WIRE.pack(can_id, len(data), data))
            except OSError as error:
                node.log(f"node {node.node}: send failed: {error.strerror}")

    if priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except OSError as error:
            node.log(f"node {node.node}: SCHED_FIFO {priority} refused ({error.strerror}): normal priority")
    start = time.monotonic()
    node.log(f"node {node.node}: emulated CiA 402 drive on {interface} ({node.identity.describe()})")
    send(node.boot(start))
    buffer = bytearray(16)
    while not stopping and not (stop_after_s and time.monotonic() - start > stop_after_s):
        try:
            sock.recv_into(buffer)
            can_id, length, data = WIRE.unpack(buffer)
            send(node.receive(can_id & 0x1FFFFFFF, data[:length], time.monotonic()))
        except TimeoutError:
            pass
        send(node.tick(time.monotonic()))
    node.log(f"node {node.node}: emulator stopped (drive {cia402.state_name(node.drive.state)})")
    sock.close()
    return 0


def logger(stream: TextIO) -> Callable[[str], None]:
    def log(text: str) -> None:
        stream.write(f"{time.strftime('%H:%M:%S')} {text}\n")
        stream.flush()

    return log


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--node", type=int, default=0, help="canopen: the node id, 1..127 (with --app: the app's)")
    parser.add_argument("--sync-timeout-ms", type=float, default=100.0,
                        help="canopen: without a SYNC this long, an enabled drive quick-stops by itself")
