"""CiA 402 servo drives on EtherCAT: ``kind = "ethercat"``.

    [devices.arm]
    kind = "ethercat"
    task = "controller"
    interface = "eth1"                 # the port the slaves hang on (a veth end for emulated drives)
    joints = [
      { name = "pan", vendor = 0xA7E, product = 0x402402, revision = 0x10000, mode = "csp",
        counts_per_rev = 4096, gear_ratio = 19.0 },
      { name = "tilt", vendor = 0xA7E, product = 0x402402, revision = 0x10000, mode = "csp",
        counts_per_rev = 4096, gear_ratio = 76.0, direction = -1 },
    ]

Before anything starts (``check``, in the supervisor) SOEM, through pysoem, scans the bus and
each slave is checked against its joint: vendor, product, revision, and the PDO mapping its SII
describes. In the task's process (``configure``) pysoem configures the slaves again, maps their
process data (SII), and takes them INIT → PRE-OP → SAFE-OP; then to OP, a thread in C keeping the
process data flowing with the drives disabled until T0 (a slave in OP must get process data within
its SM watchdog time; a Python thread would wait on the GIL behind the task's start-up work, longer
than a watchdog allows). From T0 one LRW frame per cycle, built once and sent on rtloop's own raw
socket (``read``), carries every drive's controlword and target out and its statusword and
actual values back; the CiA 402 state machine (``io/drives/cia402.py``) enables the drives on the
first exchanges. Where a slave has distributed clocks (``io/drives/ethercat_dc.py``, docs/drives.md),
SOEM configures them before SAFE-OP, the frame carries the reference clock's time to the others
(an FRMW after the LRW, its working counter checked), and each slave rtloop runs on DC gets SYNC0
started on a release T0 + kP, cycling with the period. A frame not back within ``timeout_us``
is a fault, or with ``lost_frames_max`` one of a bounded number of lost frames in a row
(``io/drives/ethercat_lost.py``). On every way the run ends: quick stop, then disable voltage,
then SAFE-OP. When the task process is killed, the slaves' SM watchdog (``watchdog_ms``) takes
them out of OP and the drives quick-stop by themselves.
"""

from __future__ import annotations

import socket
import struct
import time
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from rtloop.errors import DeviceError, DeviceFault, DeviceMismatch
from rtloop.io.cansocket import ReadableWait
from rtloop.io.compiled import devio
from rtloop.io.device import Claim, CommandLimit, Device, FloatVector, Setting, positive
from rtloop.io.drives import ethercat_dc as dc
from rtloop.io.drives.cycle import DC_LOST, NOT_LINKED, DriveCycle, command_names, reading_names
from rtloop.io.drives.ethercat_lost import blind_bound_problem, lost_frames_fault, lost_frames_note, lost_frames_span
from rtloop.io.drives.ethercat_twin import EthercatTwin
from rtloop.io.drives.joints import (
    QUICK_STOP_TIMEOUT,
    JointError,
    joint_from_table,
    joint_limits,
    joint_tables_check,
)
from rtloop.io.drives.rawsocket import (
    MAX_DATAGRAM_DATA,
    RAW_SOCKET_PERMISSION,
    interface_problem,
    new_frame,
    open_raw,
    put_datagram,
)
from rtloop.io.drives.safe_transition import safe_transition
from rtloop.io.drives.sii import parse_sii

__all__ = ["EthercatDevice", "EthercatTwin"]

LRW, BWR, FPRD = 12, 8, 4
DATA_AT = 26  # Ethernet header 14, EtherCAT header 2, datagram header 10
AL_SAFEOP, AL_OP, AL_ACK = 4, 8, 0x10
OP_WAIT_S = 10.0
"""How long configure waits for every slave to reach OP."""


def _eeprom_reader(slave: Any) -> Any:
    return lambda word: bytes(slave.eeprom_read(word))


class EthercatDevice(Device):
    """CiA 402 drives on one EtherCAT segment: SOEM configures, one LRW frame per cycle exchanges."""

    kind: ClassVar[str] = "ethercat"
    settings: ClassVar[dict[str, Setting]] = {
        "interface": Setting(str, doc="the network interface the slaves are on (eth1; a veth end for emulated drives)"),
        "joints": Setting(list, doc="one table per drive, in bus order",
                      check=joint_tables_check("name, vendor, product, revision, mode")),
        "timeout_us": Setting(float, 1000.0, "how long a cycle's frame may take to come back, µs", positive,
                              at_most=1e6),
        "watchdog_ms": Setting(float, 100.0, "the slaves' SM watchdog: without process data this long, a slave "
                               "leaves OP and its drive stops", positive, at_most=6000.0),
        "lost_frames_max": Setting(int, 0, "cycles in a row whose frame may not come back within timeout_us, each "
                                   "a lost frame (readings held, frame_ok 0, counted) before that is a fault; 0: "
                                   "the first is", lambda v: None if v >= 0 else f"expected 0 or more, got {v}",
                                   at_most=1e6),
        "quick_stop_timeout_s": QUICK_STOP_TIMEOUT,
        "emulator_interface": Setting(str, "", "the veth end `rtloop emulate ethercat --app` answers on (tests, "
                                      "examples)"),
        "sync0_shift_us": Setting(float, 0.0, "SYNC0 this long after each release, µs (distributed clocks: e.g. "
                                  "once the frame has passed every slave)", lambda v: None if v >= 0 else
                                  f"expected 0 or more, got {v}", at_most=1e6),
        "esi_dir": Setting(str, "", "the folder relative esi paths are taken from (in an app file, \".\" is the "
                           "app file's folder; default: the current folder)", is_path=True),
    }

    def __init__(self, name: str, **settings: Any) -> None:
        super().__init__(name, **settings)
        self.interface: str = settings["interface"]
        self.timeout_s: float = settings["timeout_us"] * 1e-6
        self.watchdog_ms: float = settings["watchdog_ms"]
        self.lost_frames_max: int = settings["lost_frames_max"]
        self.quick_stop_timeout_s: float = settings["quick_stop_timeout_s"]
        self.emulator_interface: str = settings["emulator_interface"]
        self.sync0_shift_ns = round(settings["sync0_shift_us"] * 1000)
        base = Path(settings["esi_dir"]) if settings["esi_dir"] else None
        try:
            self.joints = tuple(joint_from_table(table, slave, base)
                                for slave, table in enumerate(settings["joints"], start=1))
        except JointError as error:
            raise DeviceError(name, "", error.key, error.problem) from None
        names = [joint.name for joint in self.joints]
        if len(set(names)) != len(names):
            raise DeviceError(name, "", "joints", f"two joints share a name: {names}")
        self.input_names = tuple(n for joint in self.joints for n in command_names(joint))
        self.output_names = tuple(n for joint in self.joints for n in reading_names(joint)) + \
            (("frame_ok",) if self.lost_frames_max else ())  # 1: this cycle's frame came; 0: lost, readings held
        self.n_inputs, self.n_outputs = len(self.input_names), len(self.output_names)
        total = sum(j.rx.size + j.tx.size for j in self.joints)
        if total > MAX_DATAGRAM_DATA:
            raise DeviceError(name, "", "joints", f"the process data ({total} bytes) does not fit in one frame "
                              f"({MAX_DATAGRAM_DATA} bytes): fewer objects or drives per device")
        self._reset_runtime()

    def _reset_runtime(self) -> None:
        self.socket: Any = None
        self._keeper: Any = None  # the process data before T0 (io/devio_c/ecat_keeper.c FrameKeeper)
        self.cycle: DriveCycle | None = None
        self.active = False
        self._dc = dc.DcPlan()
        self._dc_wkc_at = 0
        self._t0_ns = self._period_ns = 0
        self.stale_reads = self._lost_in_a_row = self._lost_longest = 0  # lost frames (lost_frames_max)
        self._lost_since_s = 0.0
        self._frame_ok_at = self.n_outputs - 1 if self.lost_frames_max else -1

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        for key in ("socket", "cycle", "_frame", "_reply", "_commands", "_copy_commands", "_commands_from",
                    "_keeper"):
            state.pop(key, None)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._reset_runtime()

    # --- description ------------------------------------------------------------------------------
    def default_limits(self) -> dict[str, CommandLimit]:
        return joint_limits(self.joints, self.input_names or ())

    def claims(self) -> tuple[Claim, ...]:
        """The whole segment: a second master on the interface would scan, reconfigure and exchange
        with the same slaves (each frame of one master read as the other's)."""
        return (Claim(("ethercat", self.interface), "interface",
                      f"EtherCAT segment clash: {self.interface} is also"),)

    def default_twin(self) -> EthercatTwin:
        return EthercatTwin(self)

    def drive_specs(self) -> list[Any]:
        """The emulated drives this device expects (for ``rtloop emulate ethercat --app``)."""
        from rtloop.io.drives.emulator import DriveSpec

        # a joint's ESI says whether its emulated slave has distributed clocks (without one: it has)
        return [DriveSpec(j.identity, j.rx.objects, j.tx.objects, j.drive, dc=j.esi_dc is not False)
                for j in self.joints]

    # --- supervisor: the bus is there and carries the slaves the app file declares ------------------
    def _master(self) -> Any:
        try:
            import pysoem  # type: ignore[import-untyped]  # pysoem ships no type information
        except ImportError:
            raise DeviceError(self.name, "", "kind", "ethercat needs pysoem: pip install 'rtloop[ethercat]'") from None
        problem = interface_problem(self.interface)
        if problem:
            raise DeviceError(self.name, "", "interface", problem)
        try:
            open_raw(self.interface).close()
        except PermissionError:
            raise DeviceError(self.name, "", "interface", f"{self.interface}: no permission for a raw socket: "
                              f"{RAW_SOCKET_PERMISSION}") from None
        except OSError as error:
            raise DeviceError(self.name, "", "interface", f"{self.interface}: cannot open it raw: "
                              f"{error.strerror}") from None
        master = pysoem.Master()
        master.always_release_gil = True  # SOEM's waits (config, state checks) let the process's other threads run
        try:
            master.open(self.interface)
        except Exception as error:
            raise DeviceError(self.name, "", "interface", f"pysoem cannot open {self.interface}: {error}") from None
        return master

    def _scan(self, master: Any) -> None:
        found = master.config_init()
        if found <= 0:
            raise DeviceError(self.name, "", "interface", f"no EtherCAT slave answered on {self.interface} (are the "
                              "drives powered and cabled to this port? for emulated drives: is `rtloop emulate "
                              "ethercat` running on the other veth end?)")
        if found != len(self.joints):
            raise DeviceMismatch(self.name, "", "joints", f"{found} slave(s) on {self.interface}, the app file "
                                 f"declares {len(self.joints)} joints (one drive each, in bus order)")
        assign_activate: list[int] = []
        dc_units: list[bool] = []
        for joint, slave in zip(self.joints, master.slaves, strict=True):
            where = f"joints[{joint.slave - 1}]"
            for key, value in (("vendor", slave.man), ("product", slave.id), ("revision", slave.rev)):
                wanted = getattr(joint.identity, key)
                if value != wanted:
                    raise DeviceMismatch(self.name, "", f"{where}.{key}", f"slave {joint.slave} ({slave.name}) has "
                                         f"{key} 0x{value:08X}, the app file says 0x{wanted:08X}")
            info = parse_sii(_eeprom_reader(slave))
            assign_activate.append(info.dc_assign_activate)
            dc_units.append(dc.has_dc_unit(slave, info.dc_assign_activate))
            for key, found_entries, layout in (("rxpdo", info.rxpdo, joint.rx), ("txpdo", info.txpdo, joint.tx)):
                found_objects = tuple(entry.index for entry in found_entries)
                if found_objects != layout.objects:
                    missing = [f"0x{i:04X}" for i in layout.objects if i not in found_objects]
                    what = (f"object(s) {', '.join(missing)} missing from the slave's mapping" if missing else
                            "the slave maps them in another order or with others")
                    raise DeviceMismatch(self.name, "", f"{where}.{key}", f"{what}: the slave's SII maps "
                                         f"{[f'0x{i:04X}' for i in found_objects]}, the app file "
                                         f"{[f'0x{i:04X}' for i in layout.objects]}")
                bits = sum(entry.bits for entry in found_entries)
                if bits != layout.size * 8:
                    raise DeviceMismatch(self.name, "", f"{where}.{key}", f"the PDO does not fit: the slave maps "
                                         f"{bits} bits, the declared objects take {layout.size * 8}")
        self._dc, problem = dc.dc_plan(self.joints, assign_activate, dc_units)
        if problem:
            key, _, text = problem.partition(": ")
            raise DeviceMismatch(self.name, "", key, text)

    def period_problem(self, period_ns: int) -> tuple[str, str] | None:
        problem = blind_bound_problem(self.lost_frames_max, period_ns, self.watchdog_ms, round(self.timeout_s * 1e9))
        return None if problem is None else ("lost_frames_max", problem)

    def check(self) -> None:
        master = self._master()
        try:
            self._scan(master)
        finally:
            master.close()

    # --- task process: configure, OP, SAFE-OP -------------------------------------------
    def configure(self) -> None:
        import pysoem

        master = self._master()
        try:
            self._scan(master)
            for slave in master.slaves:
                slave.set_watchdog("processdata", self.watchdog_ms)
            size = master.config_map()
            cycle = DriveCycle(self.name, self.joints)
            if size != cycle.output_bytes + cycle.input_bytes:
                raise DeviceError(self.name, "", "joints", f"SOEM mapped {size} bytes of process data, the joints "
                                  f"declare {cycle.output_bytes + cycle.input_bytes}")
            self._expected_wkc = master.expected_wkc
            # SOEM's ec_configdc: receive times latched, each slave's delay and offset set (system time:
            # the master's wall clock, ns since 2000); SYNC0 is started at T0's announcement (activate)
            if self._dc.with_dc and not master.config_dc():
                raise DeviceError(self.name, "", "joints", "SOEM found no slave with distributed clocks, the "
                                  f"slaves' SII describe {self._dc.with_dc}")
            if master.state_check(pysoem.SAFEOP_STATE, 2_000_000) != pysoem.SAFEOP_STATE:
                raise DeviceError(self.name, "", "", f"the slaves did not reach SAFE-OP: {self._al_problems(master)}")
        finally:
            master.close()
        # blocking, the kernel's receive timeout one tick: one send and one recv a cycle, the frame's
        # timeout checked on the clock (a poll before each recv would cost a syscall a cycle)
        self._bind(cycle, open_raw(self.interface, receive_timeout_us=1))
        self._to_op()

    def _to_op(self) -> None:
        """SAFE-OP → OP before T0, the process data kept flowing until T0 by a thread in C (the drives
        disabled in it): the first exchange at T0 finds every slave in OP. Without the C build, OP is
        asked for at T0 instead (a Python thread would wait on the GIL longer than a watchdog allows)."""
        cycle, compiled = self.cycle, devio()
        assert cycle is not None
        if compiled is None:
            return
        cycle.waiting_outputs()
        interval_ns = round(min(1e6, self.watchdog_ms * 1e6 / 4))  # well within the SM watchdog
        keeper = compiled.FrameKeeper(self.socket.fileno(), self._frame, self._wkc_at, interval_ns,
                                      round(self.timeout_s * 1e9))
        try:
            keeper.start()
        except OSError:  # no thread here (a SCHED_DEADLINE task's process cannot make one): OP at T0
            return
        self._keeper = keeper
        self._request_state(AL_OP)
        deadline = time.monotonic() + OP_WAIT_S
        while keeper.state()[1] != self._expected_wkc:  # every slave exchanges both ways: every slave in OP
            if time.monotonic() > deadline:
                keeper.stop()
                self._keeper = None
                raise DeviceError(self.name, "", "interface", f"the slaves did not reach OP within {OP_WAIT_S:g} s "
                                  f"(working counter {keeper.state()[1]}, expected {self._expected_wkc}): "
                                  f"{self._al_states()}")
            time.sleep(0.001)

    def _al_states(self) -> str:
        """Each slave's AL status and status code, read by FPRD (outside the loop)."""
        states = []
        for joint in self.joints:
            frame = new_frame(12 + 6)
            put_datagram(frame, 16, FPRD, 0x5A, (0x1000 + joint.slave) | 0x0130 << 16, 6)  # AL status .. code
            try:
                self.socket.send(frame)
                self._sent_at = time.monotonic()
                wkc = self._receive(FPRD, 0x5A, 6)
            except OSError:
                wkc = -1
            status, _, code = struct.unpack_from("<HHH", self._reply, DATA_AT)
            states.append(f"slave {joint.slave} in AL state 0x{status:02X}, AL status code 0x{code:04X}" if wkc == 1
                          else f"slave {joint.slave} not answering")
        return "; ".join(states)

    @staticmethod
    def _al_problems(master: Any) -> str:
        master.read_state()
        return "; ".join(f"slave {i} ({slave.name}) in state 0x{slave.state:02X}, AL status code "
                         f"0x{slave.al_status:04X}" for i, slave in enumerate(master.slaves, start=1)) or "no slaves"

    def _bind(self, cycle: DriveCycle, sock: Any) -> None:
        """The cycle's frame, exchanged on ``sock`` (blocking, its receive timeout short: SO_RCVTIMEO)."""
        total_out, total = cycle.output_bytes, cycle.output_bytes + cycle.input_bytes
        reference = self._dc.reference
        self._frame = new_frame(12 + total + (12 + 8 if reference else 0))
        after = put_datagram(self._frame, 16, LRW, 0, 0, total, more=bool(reference))
        if reference:  # the reference clock's system time read and written into every other DC slave (SOEM's)
            put_datagram(self._frame, after, dc.FRMW, 0, dc.station(reference) | dc.REG_SYSTEM_TIME << 16, 8)
        self._dc_wkc_at = after + 10 + 8 if reference else 0
        self._reply = bytearray(len(self._frame) + 64)
        self._wkc_at = DATA_AT + total
        cycle.bind(self._frame, DATA_AT, self._reply, DATA_AT + total_out)
        self.cycle = cycle
        self._commands = np.zeros(self.n_inputs)
        self._copy_commands: Any = None  # write(u) in C (io/_devio.c Copies), for the vector it was built for
        self._commands_from: Any = None
        self.socket = sock
        self._readable = ReadableWait(sock.fileno())  # ppoll: to the ns, and any descriptor (select stops at 1023)
        self._sent_at = 0.0
        cycle.link(self.socket.fileno(), self._frame, self._reply, self._wkc_at, self._expected_wkc,
                   round(self.timeout_s * 1e9), self._dc_wkc_at, self._dc.with_dc, self.lost_frames_max > 0)

    def _exchange(self) -> int:
        """Send the frame, take its answer; the working counter (-1: it did not come back in time)."""
        self._send()
        return self._receive()

    def _send(self) -> None:
        frame = self._frame
        frame[17] = (frame[17] + 1) & 0xFF  # the datagram's index: its answer carries it back
        self.socket.send(frame)
        self._sent_at = time.monotonic()

    def _receive(self, command: int = LRW, index: int = -1, data_bytes: int = 2) -> int:
        """The working counter of the answer to the frame just sent (``index``: its datagram's, by
        default the cycle's frame's); -1 when it did not come within ``timeout_us`` of the send (a
        late answer is seen as it comes, a lost one at the kernel's first tick after the timeout; with
        ``lost_frames_max`` at the timeout: ppoll, to the µs). Answers to earlier frames (late ones)
        are passed over, as many as come before the timeout."""
        reply, wkc_at = self._reply, self._wkc_at if command == LRW else DATA_AT + data_bytes
        index = self._frame[17] if index < 0 else index
        cycle = self.cycle
        sent_at = max(self._sent_at, cycle.linked_sent_at()) if cycle is not None else self._sent_at  # the last send
        deadline = sent_at + self.timeout_s
        precise = self.lost_frames_max > 0
        while True:
            try:
                if precise and not self._readable.wait(max(0, round((deadline - time.monotonic()) * 1e9))):
                    return -1
                size = self.socket.recv_into(reply, 0, socket.MSG_DONTWAIT if precise else 0)
            except BlockingIOError:  # a tick (SO_RCVTIMEO) before the timeout: wait on
                size = -1
            if time.monotonic() > deadline:
                return -1
            if size < 0:
                continue
            if size >= wkc_at + 2 and reply[17] == index and reply[16] == command:
                return int(reply[wkc_at] | reply[wkc_at + 1] << 8)

    def timeline(self, t0_ns: int, period_ns: int) -> None:
        self._t0_ns, self._period_ns = t0_ns, period_ns

    def activate(self) -> None:
        """T0 is known (it may be some time away): SYNC0 of the slaves on distributed clocks is
        started on a release; the process data keeps flowing until the loop's first exchange
        (:meth:`_stop_keeper`). Without the C build OP is asked for now (with any error
        acknowledged) and the enabling waits for it."""
        if self._dc.synced and self._period_ns:
            self._start_sync0()
        if self._keeper is None:
            self._request_state(AL_OP | AL_ACK)
        self.active = True

    def _start_sync0(self) -> None:
        """SYNC0 on a release (``ethercat_dc.start_on_release``), on a socket of its own: the keeper
        thread receives on the cycle's."""
        try:
            with open_raw(self.interface, timeout_s=0.005) as sock:
                dc.start_on_release(sock, self._dc, self._t0_ns, self._period_ns, self.sync0_shift_ns)
        except (OSError, ValueError) as error:
            raise DeviceFault(f"devices.{self.name}: distributed clocks on {self.interface}: {error}") from None

    def run_notes(self) -> list[str]:
        """Which slaves ran on distributed clocks and which free on the frames, and why; the lost frames."""
        lost = lost_frames_note(self.stale_reads, self._lost_longest, self.lost_frames_max, self.timeout_s * 1e6)
        return [*self._dc.describe(self.joints), *([lost] if lost else [])]

    def may_read_stale(self) -> bool:
        return self.lost_frames_max > 0

    def stale_sources(self) -> dict[str, int]:
        return {"LRW frames not back within timeout_us": self.stale_reads} if self.stale_reads else {}

    def _stop_keeper(self) -> None:
        """The thread that kept the process data flowing since configure stops (at the loop's first
        exchange, or on the way out). A slave that left OP meanwhile is asked again, an error
        acknowledged, and the enabling waits for it."""
        keeper, self._keeper = self._keeper, None
        if keeper is not None:
            keeper.stop()
            if keeper.state()[1] != self._expected_wkc and self.socket is not None:
                self._request_state(AL_OP | AL_ACK)

    # --- the cycle ----------------------------------------------------------------------------------
    def write(self, u: FloatVector) -> None:
        if u is self._commands_from:
            self._copy_commands.run()
            return
        np.copyto(self._commands, u)
        self._commands_from = self._copy_commands = None
        compiled = devio()
        if compiled is not None:  # the task's vector is the same every cycle: copied in C from the next one on
            try:
                self._copy_commands = compiled.Copies([(u, self._commands)])
                self._commands_from = u
            except (TypeError, ValueError, BufferError):  # not a contiguous float64 vector: numpy copies
                pass

    def read(self, y: FloatVector) -> None:
        self._send_outputs()
        self._take_answer(y)

    def _send_outputs(self) -> None:
        """The first half of :meth:`read`: the outputs packed, the frame sent (one C call while
        every drive is enabled)."""
        cycle = self.cycle
        assert cycle is not None
        if not cycle.send_linked(self._commands):  # the C cycle runs once enabled: never with the keeper on
            if self._keeper is not None:  # the loop's first exchange, at T0
                self._stop_keeper()
            cycle.prepare_outputs(self._commands)
            self._send()

    def _take_answer(self, y: FloatVector) -> None:
        """The answer to the frame just sent, checked, into ``y`` (the second half of :meth:`read`)."""
        cycle = self.cycle
        assert cycle is not None
        wkc = cycle.receive_linked(y)  # one C call while every drive is enabled
        if wkc == -1:
            if self._frame_ok_at >= 0:
                self._lost_in_a_row = 0
                y[self._frame_ok_at] = 1.0
            return
        if wkc == DC_LOST:
            raise DeviceFault(self._reference_problem())
        if wkc == NOT_LINKED:
            wkc = self._receive()
        if wkc < 0:  # not back within timeout_us (-1 here, -2 from C)
            self._frame_lost(y)
            return
        # while the drives are enabled, every slave must exchange; before, a slave still on its way
        # to OP writes no outputs (the drives stay disabled: the enabling waits, within its limit)
        if wkc != self._expected_wkc and cycle.enabled:
            raise DeviceFault(self._bus_problem(wkc))
        at = self._dc_wkc_at
        if at and self._reply[at] | self._reply[at + 1] << 8 != self._dc.with_dc:
            raise DeviceFault(self._reference_problem())
        cycle.take_inputs(y)
        if self._frame_ok_at >= 0:
            self._lost_in_a_row = 0
            y[self._frame_ok_at] = 1.0

    def _frame_lost(self, y: FloatVector) -> None:
        """This cycle's frame did not come back in time: a fault, or (``lost_frames_max``) a lost
        frame: the readings not taken, frame_ok 0, counted (``io/drives/ethercat_lost.py``)."""
        cycle = self.cycle
        assert cycle is not None
        self._lost_in_a_row += 1
        sent_s = max(self._sent_at, cycle.linked_sent_at())  # this lost frame's send
        if self._lost_in_a_row == 1:
            self._lost_since_s = sent_s
        # releases skipped between lost frames (the host stalled) stretch the time without the drives:
        # the bound is N periods' sends, not only N frames
        spans = lost_frames_span(sent_s - self._lost_since_s, self._period_ns)
        if self._lost_in_a_row > self.lost_frames_max or spans > self.lost_frames_max:
            raise DeviceFault(lost_frames_fault(f"devices.{self.name}: exchange {cycle.exchanges} on {self.interface}",
                                                self._lost_in_a_row, self.timeout_s * 1e6, self.lost_frames_max,
                                                spans))
        cycle.count_lost()
        self.stale_reads += 1
        self._lost_longest = max(self._lost_longest, self._lost_in_a_row)
        y[self._frame_ok_at] = 0.0

    def _reference_problem(self) -> str:
        cycle = self.cycle
        assert cycle is not None
        at = self._dc_wkc_at
        got = self._reply[at] | self._reply[at + 1] << 8
        return (f"devices.{self.name}: exchange {cycle.exchanges} on {self.interface}: the reference clock's time "
                f"did not come back (distributed clocks: the FRMW of slave {self._dc.reference}'s system time had "
                f"working counter {got}, expected {self._dc.with_dc}): the reference clock lost or out of step")

    def _bus_problem(self, wkc: int) -> str:
        cycle = self.cycle
        assert cycle is not None
        where = f"devices.{self.name}: exchange {cycle.exchanges} on {self.interface}"
        lost = self._lost_slaves()
        who = f"; not answering: {lost}" if lost else ""
        return (f"{where}: working counter {wkc}, expected {self._expected_wkc} (every slave +3): a slave did not "
                f"exchange its process data (lost, or out of OP){who}")

    def _lost_slaves(self) -> str:
        """Which joints' slaves do not answer a read of their AL status (outside the loop: a fault)."""
        lost = []
        for joint in self.joints:
            frame = new_frame(12 + 2)
            put_datagram(frame, 16, FPRD, 0x5A, (0x1000 + joint.slave) | 0x0130 << 16, 2)  # its AL status
            try:
                self.socket.send(frame)
                self._sent_at = time.monotonic()
                answered = self._receive(FPRD, 0x5A) == 1
            except OSError:
                answered = False
            if not answered:
                lost.append(f"joint {joint.name!r} (slave {joint.slave})")
        return ", ".join(lost)

    def write_safe_for_dead_task(self, u: FloatVector) -> str:
        """Nothing is sent from the supervisor (a second master's frames would be the slaves' process
        data): each slave's SM watchdog takes it out of OP, and its drive stops by itself."""
        return (f"leaves the drives to the slaves' SM watchdog: without process data for {self.watchdog_ms:g} ms "
                "each slave leaves OP and its drive quick-stops by itself")

    # --- every way out ------------------------------------------------------------------------------
    def write_safe(self, u: FloatVector) -> None:
        """The safe transition (``io/drives/safe_transition.py``), then SAFE-OP; a fault when it did
        not finish in time. Before T0 the drives are disabled already."""
        cycle = self.cycle
        if cycle is None or not self.active:
            return
        self._stop_keeper()  # (stopped at the first exchange already, unless the run ended before it)
        self.active = False
        problem = safe_transition(cycle, lambda: self._exchange() >= 0, self.n_outputs, self.quick_stop_timeout_s,
                                  f"frames not back within {self.timeout_s * 1e6:.0f} µs", "SAFE-OP asked for: each "
                                  "slave's SM watchdog stops its drive when the frames stop")
        self._request_state(AL_SAFEOP)
        if problem:
            raise DeviceFault(f"devices.{self.name}: {problem}")

    def _request_state(self, state: int) -> None:
        frame = new_frame(12 + 2)
        put_datagram(frame, 16, BWR, 0x5B, 0x0120 << 16, 2)
        struct.pack_into("<H", frame, DATA_AT, state)
        try:
            self.socket.send(frame)
        except OSError:
            pass

    def close(self) -> None:
        keeper, self._keeper = self._keeper, None
        if keeper is not None:  # not _stop_keeper: no OP asked for on the way out
            keeper.stop()
        if self._dc.mapped_at_ns and not self._dc.slide:  # how far SYNC0 slid against the releases
            try:
                with open_raw(self.interface, timeout_s=0.005) as sock:
                    dc.measure_slide(sock, self._dc)
            except OSError as error:
                self._dc.slide = f"the reference clock's drift was not measured at the end: {error}"
        if self.socket is not None:
            self._request_state(AL_SAFEOP)
            self.socket.close()
        self.socket = None
        self.cycle = None
        self.active = False
