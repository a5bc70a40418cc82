"""CiA 402 servo drives on CANopen: ``kind = "canopen402"``.

    [devices.axis]
    kind = "canopen402"
    task = "controller"
    interface = "can0"                      # vcan0 for the emulated node
    joints = [
      { name = "wheel", node = 3, vendor = 0xA7E, product = 0x402402, revision = 0x10000, mode = "csv",
        counts_per_rev = 4096, gear_ratio = 10.0, rxpdo = ["0x6040", "0x6060", "0x60FF"],
        txpdo = ["0x6041", "0x6061", "0x6064", "0x606C"] },
    ]

A joint's table is the EtherCAT device's (``io/drives/joints.py``) plus ``node`` (its node id) and
optionally ``eds`` (its EDS file, read with the ``canopen`` package: identity, and that every
mapped object is in its dictionary) and ``sdo`` (the drive's own values, any length). Before T0, in
the task's process (``configure``): NMT reset communication and the boot-up message, the identity
(0x1018) read by SDO and checked, the PDO mapping written by SDO (each PDO synchronous), the
heartbeat producer time (0x1017) and consumer (0x1016: rtloop's heartbeat, which the cycle sends),
the ``sdo`` values (segmented beyond 4 bytes) read back; the drive cycle's C build. At T0 NMT
start. Each cycle (``read``): the RPDOs, then SYNC; the node answers with its TPDOs, which are
unpacked by the same :class:`~rtloop.io.drives.cycle.DriveCycle` as EtherCAT's (the CiA 402
state machine, SI units). Frames go out on a raw SocketCAN socket and come in through rtloop's
CAN receiver (``io/cansocket.py``, its drain in C where built). An EMCY, a heartbeat that stops
or says the node left operational, a TPDO that does not come after SYNC: each a named fault. On
every way out: quick stop, then disable voltage, then NMT pre-operational; when the task process
is killed the supervisor sends NMT stop, and the drive's own SYNC or heartbeat watch stops it.
"""

from __future__ import annotations

import importlib
import io
import logging
import time
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import numpy as np

from rtloop.errors import DeviceError, DeviceFault, DeviceMismatch
from rtloop.io.device import Claim, CommandLimit, Device, FloatVector, Setting, positive
from rtloop.io.drives import canopen_wire as wire
from rtloop.io.drives.canopen_sdo import SdoDownload, SdoTransfer, SdoUpload
from rtloop.io.drives.cycle import DriveCycle, command_names, reading_names
from rtloop.io.drives.joints import (
    QUICK_STOP_TIMEOUT,
    JointConfig,
    JointError,
    joint_from_table,
    joint_limits,
    joint_tables_check,
    read_description_file,
)
from rtloop.io.drives.pdo import OBJECTS
from rtloop.io.drives.safe_transition import safe_transition
from rtloop.runnable import Runnable

__all__ = ["Canopen402Device"]

_Transfer = TypeVar("_Transfer", bound=SdoTransfer)
CONSUMER_PERIODS = 3
"""Heartbeat periods either side waits without one before it stops (rtloop: a fault; a drive: 0x1016)."""
DATA_AT = 8


def _node_id(value: int) -> str | None:
    return None if 1 <= value <= 127 else f"expected a node id 1..127, got {value}"


def read_eds(path: Path, node: int, where: str) -> tuple[dict[str, int], set[int]]:
    """An EDS file's identity (vendor, product, revision) and the object indices it describes."""
    data = read_description_file(path, f"{where}.eds", "an EDS file")
    try:
        # by name: the optional package's types are not rtloop's to check (it may be absent)
        import_od: Any = importlib.import_module("canopen.objectdictionary").import_od
    except ImportError:
        raise JointError(f"{where}.eds", "reading an EDS file needs the canopen package: "
                         "pip install 'rtloop[canopen]'") from None
    source = io.StringIO(data.decode("utf-8", errors="replace"))
    source.name = str(path)  # the parser picks the format by the name's suffix
    # the parser logs what it skips (a data type it does not know, ...) to stderr, a line each: the
    # answer is ours to give, in one line
    parser_log = logging.getLogger("canopen")
    level = parser_log.level
    parser_log.setLevel(logging.CRITICAL)
    try:
        od = import_od(source, node)
        info = od.device_information
        identity = {"vendor": info.vendor_number, "product": info.product_number, "revision": info.revision_number}
        indices = {int(index) for index in od.indices}
    except Exception as error:  # the parser raises many kinds on a broken file: all mean "does not parse"
        raise JointError(f"{where}.eds", f"{path}: not an EDS file rtloop reads ({type(error).__name__}: "
                         f"{error})") from None
    finally:
        parser_log.setLevel(level)
    for key, value in identity.items():
        if isinstance(value, int) and not 0 <= value <= 0xFFFFFFFF:  # 0x1018's entries: 32 bits each
            raise JointError(f"{where}.eds", f"{path}: its {key} number {value} is not a 32-bit number "
                             "(0x1018, [DeviceInfo])")
    return {key: value for key, value in identity.items() if isinstance(value, int)}, indices


def sdo_writes_from(value: Any, where: str) -> tuple[tuple[int, int, bytes], ...]:
    """A joint's ``sdo`` list: ``{ index, sub (0), and one of text = "...", hex = "01 02 ...", or value = N
    with size = 1, 2, 4 (default) or 8 bytes }`` each, as (index, subindex, bytes)."""
    if not isinstance(value, list):
        raise JointError(where, "expected a list of tables: [{ index = 0x2000, sub = 0, text = \"...\" }, ...]")
    writes = []
    for position, item in enumerate(value):
        at = f"{where}[{position}]"
        if not isinstance(item, dict):
            raise JointError(at, "expected a table: { index = 0x2000, sub = 0, text = \"...\" }")
        unknown = sorted(set(item) - {"index", "sub", "text", "hex", "value", "size"})
        index, sub = item.get("index"), item.get("sub", 0)
        kinds = [key for key in ("text", "hex", "value") if key in item]
        if unknown or len(kinds) != 1:
            raise JointError(at, f"unknown key {unknown[0]!r}" if unknown else
                             "expected exactly one of text, hex or value (with size)")
        if isinstance(index, bool) or not isinstance(index, int) or not 0x1000 <= index <= 0xFFFF:
            raise JointError(f"{at}.index", f"expected an object index 0x1000..0xFFFF, got {index!r}")
        managed = _managed_by_rtloop(index)
        if managed:
            raise JointError(f"{at}.index", f"0x{index:04X} ({managed}) is rtloop's to configure, from the app file's "
                             "other settings: written after them, it would undo them")
        if isinstance(sub, bool) or not isinstance(sub, int) or not 0 <= sub <= 0xFF:
            raise JointError(f"{at}.sub", f"expected a subindex 0..255, got {sub!r}")
        data, kind = b"", kinds[0]
        if kind == "text" and isinstance(item["text"], str):
            data = item["text"].encode()
        elif kind == "hex" and isinstance(item["hex"], str):
            try:
                data = bytes.fromhex(item["hex"])
            except ValueError:
                raise JointError(f"{at}.hex", f"{item['hex']!r} is not bytes in hex (\"01 a0 ff\")") from None
        elif kind == "value":
            number, size = item["value"], item.get("size", 4)
            if size not in (1, 2, 4, 8) or isinstance(size, bool):
                raise JointError(f"{at}.size", f"expected 1, 2, 4 or 8 bytes, got {size!r}")
            if isinstance(number, bool) or not isinstance(number, int) or \
                    not -(1 << (8 * size - 1)) <= number < 1 << (8 * size):
                raise JointError(f"{at}.value", f"expected a whole number that fits {size} bytes, got {number!r}")
            data = (number & ((1 << (8 * size)) - 1)).to_bytes(size, "little")
        else:
            raise JointError(f"{at}.{kind}", f"expected a string, got {item[kind]!r}")
        writes.append((index, sub, data))
    return tuple(writes)


def _managed_by_rtloop(index: int) -> str | None:
    """What an object rtloop configures itself is (the sdo list may not write it), or None. 0x1016 was
    writable: sdo = [{ index = 0x1016, sub = 1, value = 0 }] switched off the drive's watch of rtloop's
    heartbeat, the drive's way to stop when the task dies; the PDO objects undid the mapping."""
    if index in (0x1016, 0x1017):
        return "the heartbeat consumer and producer"
    if 0x1400 <= index <= 0x1BFF:
        return "a PDO's communication or mapping parameters"
    if index in OBJECTS:
        return f"{OBJECTS[index].name}, a process data object rtloop drives"
    return None


class _Node:
    """One joint's node: its id, its frames, where its TPDOs go in the inputs."""

    def __init__(self, node: int, joint: JointConfig, sdo_writes: tuple[tuple[int, int, bytes], ...] = ()) -> None:
        self.node = node
        self.joint = joint
        self.sdo_writes = sdo_writes
        self.rx_chunks = wire.pdo_chunks(joint.rx)
        self.tx_chunks = wire.pdo_chunks(joint.tx)


class Canopen402Device(Device):
    """CiA 402 drives on one CAN bus: SDO configuration before T0, SYNC and PDOs every cycle."""

    kind: ClassVar[str] = "canopen402"
    settings: ClassVar[dict[str, Setting]] = {
        "interface": Setting(str, doc="the SocketCAN interface the drives are on (can0; vcan0 for the emulated node)"),
        "joints": Setting(list, doc="one table per drive: its joint and its node id",
                      check=joint_tables_check("name, node, vendor, product, revision, mode")),
        "answer_timeout_ms": Setting(float, 500.0, "how long a node may take to answer an SDO or to boot up after "
                                     "NMT reset, ms", positive, at_most=60_000.0),
        "tpdo_timeout_ms": Setting(float, 1.0, "how long after SYNC the TPDOs may take to come, ms", positive,
                                   at_most=10_000.0),
        "heartbeat_ms": Setting(float, 100.0, "the heartbeat period of the nodes (0x1017) and of rtloop's own; "
                                "either side stops after three missed", positive, at_most=20_000.0),
        "master_node": Setting(int, 127, "the node id rtloop's own heartbeat goes out as (0x700 + it), which "
                               "each drive's heartbeat consumer (0x1016) watches", _node_id),
        "quick_stop_timeout_s": QUICK_STOP_TIMEOUT,
        "eds_dir": Setting(str, "", "the folder relative eds paths are taken from (in an app file, \".\" is the "
                           "app file's folder)", is_path=True),
    }

    def __init__(self, name: str, **settings: Any) -> None:
        super().__init__(name, **settings)
        self.interface: str = settings["interface"]
        self.answer_timeout_s: float = settings["answer_timeout_ms"] / 1000.0
        self.tpdo_timeout_ms: float = settings["tpdo_timeout_ms"]
        self.heartbeat_ms: float = settings["heartbeat_ms"]
        self.quick_stop_timeout_s: float = settings["quick_stop_timeout_s"]
        self.master_node: int = settings["master_node"]
        base = Path(settings["eds_dir"]) if settings["eds_dir"] else None
        nodes = []
        try:
            for position, given in enumerate(settings["joints"], start=1):
                nodes.append(self._node_from_table(dict(given), position, base))
        except JointError as error:
            raise DeviceError(name, "", error.key, error.problem) from None
        self.nodes = tuple(nodes)
        self.joints = tuple(node.joint for node in self.nodes)
        for key, values in (("name", [j.name for j in self.joints]), ("node", [n.node for n in self.nodes])):
            if len(set(values)) != len(values):
                raise DeviceError(name, "", "joints", f"two joints share a {key}: {values}")
        if self.master_node in [n.node for n in self.nodes]:
            raise DeviceError(name, "", "master_node", f"{self.master_node} is also a joint's node id: rtloop's "
                              "heartbeat would be taken for that drive's")
        self.input_names = tuple(n for joint in self.joints for n in command_names(joint))
        self.output_names = tuple(n for joint in self.joints for n in reading_names(joint))
        self.n_inputs, self.n_outputs = len(self.input_names), len(self.output_names)
        self._reset_runtime()

    @staticmethod
    def _node_from_table(table: dict[str, Any], position: int, base: Path | None) -> _Node:
        where = f"joints[{position - 1}]"
        node = table.pop("node", None)
        if isinstance(node, bool) or not isinstance(node, int) or not 1 <= node <= 127:
            raise JointError(f"{where}.node", f"expected the drive's node id 1..127, got {node!r}")
        if "dc" in table:
            raise JointError(f"{where}.dc", "distributed clocks are EtherCAT's: a CANopen drive follows SYNC")
        eds = table.pop("eds", None)
        sdo_writes = sdo_writes_from(table.pop("sdo", []), f"{where}.sdo")
        indices: set[int] = set()
        if eds is not None:
            path = Path(str(eds))
            if base is not None and not path.is_absolute():
                path = base / path
            identity, indices = read_eds(path, node, where)
            for key, value in identity.items():
                table.setdefault(key, value)
        joint = joint_from_table(table, position)
        for key, layout in (("rxpdo", joint.rx), ("txpdo", joint.tx)):
            try:
                wire.pdo_chunks(layout)
            except ValueError as error:
                raise JointError(f"{where}.{key}", str(error)) from None
            missing = [f"0x{i:04X} ({OBJECTS[i].name})" for i in layout.objects if indices and i not in indices]
            if missing:
                raise JointError(f"{where}.{key}", f"{', '.join(missing)} not in the EDS file {eds}: the drive "
                                 "does not have it")
        return _Node(node, joint, sdo_writes)

    def _reset_runtime(self) -> None:
        self.socket: Any = None
        self.cycle: DriveCycle | None = None
        self.active = False

    def __getstate__(self) -> dict[str, Any]:
        # travels to the task process unopened: sockets and the per-cycle views are made there
        state = {key: value for key, value in self.__dict__.items() if not key.startswith("_")}
        state.update(socket=None, cycle=None, active=False)
        return state

    # --- description ----------------------------------------------------------------------------
    def default_limits(self) -> dict[str, CommandLimit]:
        return joint_limits(self.joints, self.input_names or ())

    def claims(self) -> tuple[Claim, ...]:
        """The bus's NMT master and SYNC producer, and each node's requests: a second master would
        reconfigure the nodes and interleave its SYNCs with ours."""
        ids = [0x000, wire.SYNC_ID, wire.heartbeat_id(self.master_node)] + [cob for n in self.nodes for cob in
                                       (wire.sdo_request_id(n.node),
                                        *(wire.rpdo_id(n.node, i) for i in range(len(n.rx_chunks))))]
        return tuple(Claim(("can", self.interface, cob), "joints", f"CANopen id clash: 0x{cob:X} on "
                           f"{self.interface} is also", "sent") for cob in ids)

    def default_twin(self) -> Runnable:
        from rtloop.io.drives.ethercat import EthercatTwin

        # the same drive model stepped in the same order (TPDOs hold the values before the step)
        return EthercatTwin(self)  # it reads name, joints and the names only

    # --- supervisor ------------------------------------------------------------------------------
    def check(self) -> None:
        from rtloop.io.cansocket import CanInterfaceError, can_supported, check_interface

        unsupported = can_supported()
        if unsupported:
            raise DeviceError(self.name, "", "interface", f"{self.interface!r}: {unsupported}")
        try:
            check_interface(self.interface, False, "interface")
        except CanInterfaceError as error:
            raise DeviceError(self.name, "", "interface", str(error).partition(": ")[2]) from None

    # --- task process: configure ------------------------------------------------------------------
    def _receive_frames(self) -> list[Any]:
        from rtloop.io.canframes import frame_from_table

        tiny = 1e-6  # frames nobody waits for: taken when they are there
        tables = []
        for n in self.nodes:
            tables += [(wire.tpdo_id(n.node, i), self.tpdo_timeout_ms) for i in range(len(n.tx_chunks))]
        for n in self.nodes:
            tables += [(wire.emcy_id(n.node), tiny), (wire.heartbeat_id(n.node), tiny),
                       (wire.sdo_answer_id(n.node), tiny)]
        return [frame_from_table({"id": cob, "timeout_ms": timeout}, f"joints.0x{cob:X}", False, True)
                for cob, timeout in tables]

    def open_socket(self, frames: list[Any]) -> Any:
        from rtloop.io.cansocket import CanInterfaceError, CanSocket

        try:
            return CanSocket(self.interface, False, frames, f"devices.{self.name}")
        except CanInterfaceError as error:
            raise DeviceError(self.name, "", "interface", str(error).partition(": ")[2]) from None

    def configure(self) -> None:
        frames = self._receive_frames()
        self.socket = self.open_socket(frames)
        index = {frame.can_id: i for i, frame in enumerate(frames)}
        self._index = index
        try:
            for n in self.nodes:
                self._configure_node(n)
        except BaseException:
            self.close()
            raise
        self._bind()

    def _send(self, can_id: int, data: bytes) -> None:
        self.socket.send(wire.wire_frame(can_id, data))

    def _wait_for(self, can_id: int, accept: Any) -> Any:
        """The first frame ``can_id`` whose data ``accept`` takes (not None) within the answer timeout."""
        sock, at = self.socket, self._index[can_id]
        deadline = time.monotonic() + self.answer_timeout_s
        while True:
            sock.fresh[:] = sock.none_fresh
            sock._drain()
            if sock.fresh[at]:
                data = bytes(sock.latest[at][DATA_AT:DATA_AT + sock.latest[at][4]])
                value = accept(data)
                if value is not None:
                    return value
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            sock.readable.wait(int(min(left, 0.01) * 1e9))

    def _sdo(self, n: _Node, request: bytes, index: int, subindex: int) -> int:
        where = f"joints[{n.joint.slave - 1}]"
        self._send(wire.sdo_request_id(n.node), request)
        try:
            value = self._wait_for(wire.sdo_answer_id(n.node), lambda data: wire.sdo_answer(data, index, subindex))
        except wire.SdoAbort as abort:
            raise DeviceMismatch(self.name, "", where, f"node {n.node} refused SDO 0x{index:04X}:{subindex} "
                                 f"(abort code 0x{abort.code:08X}): the drive does not have the object, or "
                                 "not writable so") from None
        if value is None:
            raise DeviceError(self.name, "", f"{where}.node", f"node {n.node} on {self.interface} did not answer "
                              f"SDO 0x{index:04X}:{subindex} within {self.answer_timeout_s * 1e3:g} ms "
                              "(answer_timeout_ms): is the drive powered, on this bus, with this node id?")
        return int(value)

    def _transfer(self, n: _Node, transfer: _Transfer) -> _Transfer:
        """One SDO transfer of any length (segmented beyond 4 bytes) to ``n``, done: request, answer, ..."""
        where = f"joints[{n.joint.slave - 1}]"
        what = f"SDO 0x{transfer.index:04X}:{transfer.subindex}"
        while True:
            self._send(wire.sdo_request_id(n.node), transfer.request)
            try:
                done = self._wait_for(wire.sdo_answer_id(n.node), transfer.take)
            except wire.SdoAbort as abort:
                raise DeviceMismatch(self.name, "", f"{where}.sdo", f"node {n.node} refused {what} (abort code "
                                     f"0x{abort.code:08X})") from None
            if done is None:
                raise DeviceError(self.name, "", f"{where}.node", f"node {n.node} on {self.interface} did not answer "
                                  f"{what} within {self.answer_timeout_s * 1e3:g} ms (answer_timeout_ms)")
            if done:
                return transfer

    def _configure_node(self, n: _Node) -> None:
        where = f"joints[{n.joint.slave - 1}]"
        self._send(0x000, bytes([wire.NMT_RESET_COMMUNICATION, n.node]))
        booted = self._wait_for(wire.heartbeat_id(n.node), lambda data: True if data[:1] == b"\0" else None)
        if booted is None:  # a node may also come up without a boot-up message we saw: its SDO decides
            self._send(0x000, bytes([wire.NMT_PRE_OPERATIONAL, n.node]))
        identity = n.joint.identity
        for sub, key in ((1, "vendor"), (2, "product"), (3, "revision")):
            found = self._sdo(n, wire.sdo_upload(0x1018, sub), 0x1018, sub)
            wanted = getattr(identity, key)
            if found != wanted:
                raise DeviceMismatch(self.name, "", f"{where}.{key}", f"node {n.node} has {key} 0x{found:08X} "
                                     f"(0x1018:{sub}), the app file says 0x{wanted:08X}")
        for index, sub, value, size in wire.mapping_writes(n.node, n.joint.rx, n.joint.tx):
            self._sdo(n, wire.sdo_download(index, sub, value, size), index, sub)
        self._sdo(n, wire.sdo_download(0x1017, 0, round(self.heartbeat_ms), 2), 0x1017, 0)
        consumer = self.master_node << 16 | round(CONSUMER_PERIODS * self.heartbeat_ms)
        self._sdo(n, wire.sdo_download(0x1016, 1, consumer, 4), 0x1016, 1)  # watched from our first heartbeat
        for index, sub, data in n.sdo_writes:  # the app's own values, read back: a drive may clip or ignore one
            self._transfer(n, SdoDownload(index, sub, data))
            kept = self._transfer(n, SdoUpload(index, sub)).value
            # a number may come back in more bytes than written (an expedited answer without its size)
            if kept != data and (len(data) > 8 or int.from_bytes(kept, "little") != int.from_bytes(data, "little")):
                raise DeviceMismatch(self.name, "", f"{where}.sdo", f"node {n.node} kept 0x{index:04X}:{sub} as "
                                     f"{kept!r}, not the {data!r} written")

    def _bind(self) -> None:
        cycle = DriveCycle(self.name, self.joints)
        self._out = bytearray(cycle.output_bytes)
        self._in = bytearray(cycle.input_bytes)
        cycle.bind(self._out, 0, self._in, 0)
        out_view, in_view, sock = memoryview(self._out), memoryview(self._in), self.socket
        self._rpdos: list[bytearray] = []
        self._rpdo_copies: list[tuple[memoryview, memoryview]] = []
        self._tpdo_copies: list[tuple[int, memoryview, memoryview]] = []
        out_at = in_at = 0
        for n in self.nodes:
            for number, (start, length, _objects) in enumerate(n.rx_chunks):
                frame = wire.wire_frame(wire.rpdo_id(n.node, number), length=length)
                self._rpdos.append(frame)
                self._rpdo_copies.append((out_view[out_at + start:out_at + start + length],
                                          memoryview(frame)[DATA_AT:DATA_AT + length]))
            for number, (start, length, _objects) in enumerate(n.tx_chunks):
                at = self._index[wire.tpdo_id(n.node, number)]
                self._tpdo_copies.append((at, memoryview(sock.latest[at])[DATA_AT:DATA_AT + length],
                                          in_view[in_at + start:in_at + start + length]))
            out_at += n.joint.rx.size
            in_at += n.joint.tx.size
        self._sync = wire.wire_frame(wire.SYNC_ID)
        self._emcy = [(n, self._index[wire.emcy_id(n.node)]) for n in self.nodes]
        self._heartbeats = [(n, self._index[wire.heartbeat_id(n.node)]) for n in self.nodes]
        self._heartbeat_seen_ns = [0] * len(self.nodes)
        self._heartbeat_lost_ns = round(CONSUMER_PERIODS * self.heartbeat_ms * 1e6)
        self._heartbeat = wire.wire_frame(wire.heartbeat_id(self.master_node), bytes([0x05]))  # operational
        self._heartbeat_ns = round(self.heartbeat_ms * 1e6)
        self._heartbeat_sent_ns = 0
        self._commands = np.zeros(self.n_inputs)
        self._readings = np.zeros(self.n_outputs)  # the cycle's own: its C build is made here, before T0
        cycle.compile(self._commands, self._readings)
        self.cycle = cycle

    def activate(self) -> None:
        """At T0: NMT start; what came before (boot-up, SDO answers) is dropped."""
        for n in self.nodes:
            self._send(0x000, bytes([wire.NMT_START, n.node]))
        self.socket._drain()
        now_ns = time.monotonic_ns()
        self._heartbeat_seen_ns = [now_ns] * len(self.nodes)
        self.active = True

    # --- the cycle ------------------------------------------------------------------------------
    def write(self, u: FloatVector) -> None:
        np.copyto(self._commands, u)

    def _exchange(self) -> int:
        """RPDOs, SYNC, then the TPDOs that came in time into the inputs; the start of the wait (ns)."""
        send = self.socket.sock.send
        for source, target in self._rpdo_copies:
            target[:] = source
        try:
            now_ns = time.monotonic_ns()
            if now_ns - self._heartbeat_sent_ns >= self._heartbeat_ns:  # ours, which the drives' consumers watch
                self._heartbeat_sent_ns = now_ns
                send(self._heartbeat)
            for frame in self._rpdos:
                send(frame)
            send(self._sync)
            start_ns = time.monotonic_ns()
            self.socket.receive_cycle(start_ns)
        except OSError as error:
            raise DeviceFault(f"devices.{self.name}: CAN interface {self.interface}: {error.strerror}") from None
        return start_ns

    def read(self, y: FloatVector) -> None:
        cycle = self.cycle
        assert cycle is not None
        cycle.prepare_outputs(self._commands)
        start_ns = self._exchange()
        sock = self.socket
        fresh, latest = sock.fresh, sock.latest
        for n, at in self._emcy:
            if fresh[at] and latest[at][DATA_AT] | latest[at][DATA_AT + 1]:
                raise DeviceFault(self._emcy_problem(n, bytes(latest[at][DATA_AT:DATA_AT + 8])))
        for i, (n, at) in enumerate(self._heartbeats):
            if fresh[at]:
                self._heartbeat_seen_ns[i] = start_ns
                # a heartbeat sent just before the node took NMT start may still say pre-operational:
                # once the drive is enabled (several exchanges later) any other state is the node's
                if latest[at][DATA_AT] != 0x05 and cycle.enabled:
                    raise DeviceFault(f"{self._where(n)}: the node left operational: its heartbeat says "
                                      f"{wire.HEARTBEAT_STATES.get(latest[at][DATA_AT], hex(latest[at][DATA_AT]))}, "
                                      f"exchange {cycle.exchanges}")
            elif start_ns - self._heartbeat_seen_ns[i] > self._heartbeat_lost_ns:
                raise DeviceFault(f"{self._where(n)}: heartbeat lost: none for "
                                  f"{(start_ns - self._heartbeat_seen_ns[i]) / 1e6:.0f} ms (heartbeat_ms "
                                  f"{self.heartbeat_ms:g}), exchange {cycle.exchanges}")
        for at, source, target in self._tpdo_copies:
            if not fresh[at]:
                raise DeviceFault(self._tpdo_problem(at))
            target[:] = source
        cycle.take_inputs(self._readings)
        np.copyto(y, self._readings)

    def _where(self, n: _Node) -> str:
        return f"devices.{self.name}: joint {n.joint.name!r} (node {n.node})"

    def _emcy_problem(self, n: _Node, data: bytes) -> str:
        code, register = int.from_bytes(data[:2], "little"), data[2]
        exchanges = self.cycle.exchanges if self.cycle else 0
        return (f"{self._where(n)}: EMCY 0x{code:04X} ({wire.emcy_name(code)}), error register 0x{register:02X}, "
                f"exchange {exchanges}")

    def _tpdo_problem(self, at: int) -> str:
        cob = self.socket.receive[at].can_id
        node = cob & 0x7F
        n = next(n for n in self.nodes if n.node == node)
        exchanges = self.cycle.exchanges if self.cycle else 0
        return (f"{self._where(n)}: TPDO{(cob - 0x180 - node) // 0x100 + 1} (0x{cob:X}) did not come within "
                f"{self.tpdo_timeout_ms:g} ms of SYNC (tpdo_timeout_ms), exchange {exchanges}: the node lost, "
                "or the bus too slow for the period")

    # --- every way out ----------------------------------------------------------------------------
    def write_safe(self, u: FloatVector) -> None:
        """The safe transition (``io/drives/safe_transition.py``): quick stop while enabled, disable
        voltage once at rest, then NMT pre-operational; a fault when it did not finish in time.
        Before T0 the drives are disabled already."""
        cycle = self.cycle
        if cycle is None or not self.active or self.socket is None:
            return
        self.active = False
        fresh = self.socket.fresh

        def exchange() -> bool:
            self._exchange()
            if not all(fresh[at] for at, _source, _target in self._tpdo_copies):
                return False
            for _at, source, target in self._tpdo_copies:
                target[:] = source
            return True

        problem = safe_transition(cycle, exchange, self.n_outputs, self.quick_stop_timeout_s,
                                  f"SYNCs without every TPDO within {self.tpdo_timeout_ms:g} ms", "NMT pre-operational "
                                  "sent: each drive's heartbeat consumer or SYNC watch stops it when the PDOs stop")
        for n in self.nodes:
            try:
                self._send(0x000, bytes([wire.NMT_PRE_OPERATIONAL, n.node]))
            except OSError:
                break
        if problem:
            raise DeviceFault(f"devices.{self.name}: {problem}")

    def write_safe_for_dead_task(self, u: FloatVector) -> str:
        """From the supervisor: NMT stop to each node (an operational drive quick-stops when its
        PDOs stop); the node's own SYNC or heartbeat watch stops it where this frame cannot go."""
        import socket

        try:
            sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
            try:
                sock.bind((self.interface,))
                for n in self.nodes:
                    sock.send(wire.wire_frame(0x000, bytes([wire.NMT_STOP, n.node])))
            finally:
                sock.close()
        except OSError as error:
            return (f"could not send NMT stop on {self.interface} ({error.strerror}): the drives' own SYNC or "
                    "heartbeat watch stops them")
        return f"sent NMT stop to node(s) {', '.join(str(n.node) for n in self.nodes)} on {self.interface}"

    def close(self) -> None:
        if self.socket is not None:
            self.socket.close()
        self._reset_runtime()
