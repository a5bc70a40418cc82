"""The two wire protocols, and the per-cycle packets built once on them.

Dynamixel Protocol 2.0::

    FF FF FD 00 | ID | LEN (u16) | INSTRUCTION | PARAMS ... | CRC-16 (u16)
    status:                        0x55, ERROR, PARAMS ...

LEN counts what follows it (instruction, parameters, CRC); the CRC-16 (polynomial 0x8005,
initial 0, not reflected: CRC-16/UMTS) covers everything before it; ``FF FF FD`` inside the
instruction and parameters is sent as ``FF FF FD FD`` (byte stuffing), and LEN counts the
stuffed bytes. Status error byte: bit 7 is the hardware alert, the rest an error number.

Feetech SCS/STS (Dynamixel 1.0's frame)::

    FF FF | ID | LEN (u8) | INSTRUCTION or ERROR | PARAMS ... | CHECKSUM

LEN = parameters + 2; the checksum is the complement of the byte sum from ID on. The status
error byte holds the hardware error bits.

Both: broadcast ID 0xFE; PING 1, READ 2, WRITE 3, SYNC_READ 0x82, SYNC_WRITE 0x83. A sync
write carries (address, length) then (ID, data) per servo and gets no answer; a sync read
carries (address, length, IDs) and each servo answers one status packet, in ID order.

:class:`SyncWrite` and :class:`SyncRead` are the per-cycle packets: built once, their values
written and read through numpy views on the packet's own bytes, so a cycle makes no object
that stays. :meth:`Protocol.scan` decodes one packet in place; the servo model uses it too.
The CRC-16 and the checksum are Python references here (:class:`Checks`), with compiled twins
(``io/devio_c/servo.c``) that the per-cycle packets use where they were built (:func:`for_the_cycle`);
so is the sync read's scanning loop (:meth:`SyncRead.collect`: ``servo_take_answers``).
"""

from __future__ import annotations

import time
from typing import Any
from typing import Protocol as TypingProtocol

import numpy as np

from rtloop.io.servos.tables import Field

BROADCAST_ID = 0xFE
PING, READ, WRITE, SYNC_READ, SYNC_WRITE = 0x01, 0x02, 0x03, 0x82, 0x83
DXL_STATUS = 0x55
DXL_ALERT = 0x80
DXL_HEADER = b"\xff\xff\xfd\x00"
STUFFING = b"\xff\xff\xfd"
STUFFED = b"\xff\xff\xfd\xfd"
DXL_ERRORS = {1: "result fail", 2: "instruction error", 3: "CRC error", 4: "data range error",
              5: "data length error", 6: "data limit error", 7: "access error"}
NEED_MORE = 0
BAD = -1


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data: Any, start: int = 0, end: int | None = None, crc: int = 0) -> int:
    """Dynamixel's CRC-16 (CRC-16/UMTS: ``123456789`` → 0xFEE8) of ``data[start:end]``, from ``crc``."""
    table = _CRC_TABLE
    for index in range(start, len(data) if end is None else end):
        crc = ((crc << 8) & 0xFFFF) ^ table[((crc >> 8) ^ data[index]) & 0xFF]
    return crc


def crc_matches(data: Any, start: int, end: int) -> bool:
    """The CRC-16 of ``data[start:end]`` is the little-endian u16 at ``end`` (a packet's own)."""
    return bool(crc16(data, start, end) == data[end] | data[end + 1] << 8)


def seal_crc(data: Any, start: int, end: int, crc: int) -> None:
    """Write the CRC-16 of ``data[start:end]`` (from ``crc``, that of the bytes before) at ``end``, little endian."""
    crc = crc16(data, start, end, crc)
    data[end], data[end + 1] = crc & 0xFF, crc >> 8


def byte_sum(data: Any, start: int, end: int, total: int = 0) -> int:
    """Feetech's checksum of ``data[start:end]``, after bytes that summed to ``total``."""
    for index in range(start, end):
        total += data[index]
    return ~total & 0xFF


def sum_matches(data: Any, start: int, end: int) -> bool:
    """Feetech's checksum of ``data[start:end]`` is the byte at ``end``."""
    return bool(byte_sum(data, start, end) == data[end])


def seal_sum(data: Any, start: int, end: int, total: int) -> None:
    """Write Feetech's checksum of ``data[start:end]``, after bytes that summed to ``total``, at ``end``."""
    data[end] = byte_sum(data, start, end, total)


class Checks:
    """The per-packet checks a :class:`Protocol` calls: the Python references above, or their compiled
    twins (``io/devio_c/servo.c``, the same bits) given the module ``io/_devio.c`` builds.

    The per-cycle packets of a device use the compiled ones where they were built (:func:`for_the_cycle`);
    the servo model and the set-up keep the references, so a run against the model checks one with the
    other as well."""

    def __init__(self, compiled: Any = None) -> None:
        self.compiled = compiled is not None
        self.crc16 = compiled.servo_crc16 if compiled is not None else crc16
        self.crc_matches = compiled.servo_crc_matches if compiled is not None else crc_matches
        self.seal_crc = compiled.servo_seal_crc if compiled is not None else seal_crc
        self.sum_matches = compiled.servo_sum_matches if compiled is not None else sum_matches
        self.seal_sum = compiled.servo_seal_sum if compiled is not None else seal_sum
        self.take_answers: Any = compiled.servo_take_answers if compiled is not None else None
        """A sync read's scanning loop in C (:meth:`SyncRead.collect`'s twin), or None: the loop here runs."""


def stuff(body: bytes) -> bytes:
    """``FF FF FD`` → ``FF FF FD FD`` (Dynamixel 2.0's byte stuffing)."""
    return body.replace(STUFFING, STUFFED) if STUFFING in body else body


def destuff(body: bytes) -> bytes:
    return body.replace(STUFFED, STUFFING) if STUFFED in body else body


class Line(TypingProtocol):
    """Where packets go: a serial line (:class:`~rtloop.io.servos.line.PortLine`) or a model in process."""

    def send(self, data: Any) -> None: ...

    def receive(self, buffer: memoryview, timeout_ns: int) -> int:
        """Bytes read into ``buffer`` (0: none came within ``timeout_ns``)."""
        ...

    def flush_input(self) -> None: ...


class Scan:
    """One packet found by :meth:`Protocol.scan` (attributes set in place: nothing made per packet)."""

    __slots__ = ("end", "error", "first", "instruction", "needed", "problem", "servo_id")

    def __init__(self) -> None:
        self.servo_id = self.instruction = self.error = self.first = self.end = self.needed = 0
        self.problem = ""


class Protocol:
    """What differs between the two wire formats (see the module)."""

    name = ""
    header_bytes = 0
    address_bytes = 1

    def __init__(self, checks: Checks | None = None) -> None:
        self.checks = checks or Checks()

    def packet(self, servo_id: int, instruction: int, params: bytes) -> bytearray:
        raise NotImplementedError

    def status(self, servo_id: int, error: int, params: bytes) -> bytearray:
        raise NotImplementedError

    def scan(self, buffer: Any, start: int, end: int, scan: Scan, status: bool) -> int:
        """Decode the packet at ``buffer[start:end]``: its byte count, or ``NEED_MORE`` (``scan.needed``:
        the bytes it needs from ``start``), or ``BAD`` (``scan.problem``). A status's ``scan.first`` is
        its error byte, an instruction's its first parameter; ``scan.end`` ends the parameters."""
        raise NotImplementedError

    def copy_params(self, buffer: Any, scan: Scan, target: bytearray, at: int, size: int) -> bool:
        """Copy ``buffer[scan.first:scan.end]`` (unstuffed) to ``target[at:at + size]``; False when its
        size differs."""
        if scan.end - scan.first != size:
            return False
        target[at:at + size] = buffer[scan.first:scan.end]
        return True

    def seal(self, packet: bytearray, prefix_crc: int, prefix_end: int, stuffed: bytearray) -> memoryview:
        """The bytes to send for ``packet`` once its values are in: checksum or CRC (and stuffing)."""
        raise NotImplementedError

    def range_params(self, address: int, length: int) -> bytes:
        n = self.address_bytes
        return address.to_bytes(n, "little") + length.to_bytes(n, "little")

    def max_status_bytes(self, data_bytes: int) -> int:
        raise NotImplementedError


class Dynamixel2(Protocol):
    name = "dynamixel"
    header_bytes = 7  # FF FF FD 00, ID, LEN
    address_bytes = 2

    def packet(self, servo_id: int, instruction: int, params: bytes) -> bytearray:
        body = stuff(bytes([instruction]) + params)
        length = len(body) + 2
        data = bytearray(DXL_HEADER + bytes([servo_id, length & 0xFF, length >> 8]) + body + b"\0\0")
        crc = crc16(data, 0, len(data) - 2)
        data[-2], data[-1] = crc & 0xFF, crc >> 8
        return data

    def status(self, servo_id: int, error: int, params: bytes) -> bytearray:
        return self.packet(servo_id, DXL_STATUS, bytes([error]) + params)

    def max_status_bytes(self, data_bytes: int) -> int:
        body = 2 + data_bytes
        return 7 + body + body // 3 + 1 + 2  # every third byte stuffed at worst

    def scan(self, buffer: Any, start: int, end: int, scan: Scan, status: bool) -> int:
        if end - start < 7:
            scan.needed = 7
            return NEED_MORE
        if buffer[start] != 0xFF or buffer[start + 1] != 0xFF or buffer[start + 2] != 0xFD or buffer[start + 3] != 0:
            scan.problem = "no packet header (FF FF FD 00)"
            return BAD
        total = 7 + (buffer[start + 5] | buffer[start + 6] << 8)
        if total < 10 or (status and total < 11):
            scan.problem = f"length {total - 7} too short"
            return BAD
        if end - start < total:
            scan.needed = total
            return NEED_MORE
        crc_at = start + total - 2
        if not self.checks.crc_matches(buffer, start, crc_at):
            scan.problem = "CRC mismatch"
            return BAD
        scan.servo_id, scan.instruction = buffer[start + 4], buffer[start + 7]
        if status:
            if scan.instruction != DXL_STATUS:
                scan.problem = f"instruction 0x{scan.instruction:02x} where a status (0x55) was due"
                return BAD
            scan.error = buffer[start + 8]
            scan.first = start + 8
        else:
            scan.error, scan.first = 0, start + 8
        scan.end = crc_at
        return int(total)

    def copy_params(self, buffer: Any, scan: Scan, target: bytearray, at: int, size: int) -> bool:
        if buffer.find(STUFFED, scan.first, scan.end) < 0:
            return super().copy_params(buffer, scan, target, at, size)
        plain = destuff(bytes(buffer[scan.first:scan.end]))  # rare (FF FF FD in the data): may allocate
        if len(plain) != size:
            return False
        target[at:at + size] = plain
        return True

    def seal(self, packet: bytearray, prefix_crc: int, prefix_end: int, stuffed: bytearray) -> memoryview:
        end = len(packet) - 2
        if packet.find(STUFFING, 7, end) < 0:  # the usual case: the packet as built
            self.checks.seal_crc(packet, prefix_end, end, prefix_crc)
            return memoryview(packet)
        body = stuff(bytes(packet[7:end]))  # FF FF FD in the values: rare, may allocate
        size = 7 + len(body) + 2
        stuffed[:7] = packet[:7]
        stuffed[5], stuffed[6] = (len(body) + 2) & 0xFF, (len(body) + 2) >> 8
        stuffed[7:7 + len(body)] = body
        self.checks.seal_crc(stuffed, 0, size - 2, 0)
        return memoryview(stuffed)[:size]


class Feetech(Protocol):
    name = "feetech"
    header_bytes = 4  # FF FF, ID, LEN
    address_bytes = 1

    def packet(self, servo_id: int, instruction: int, params: bytes) -> bytearray:
        data = bytearray(bytes([0xFF, 0xFF, servo_id, len(params) + 2, instruction]) + params + b"\0")
        data[-1] = ~sum(data[2:-1]) & 0xFF
        return data

    def status(self, servo_id: int, error: int, params: bytes) -> bytearray:
        return self.packet(servo_id, error, params)

    def max_status_bytes(self, data_bytes: int) -> int:
        return 6 + data_bytes

    def scan(self, buffer: Any, start: int, end: int, scan: Scan, status: bool) -> int:
        if end - start < 4:
            scan.needed = 4
            return NEED_MORE
        if buffer[start] != 0xFF or buffer[start + 1] != 0xFF:
            scan.problem = "no packet header (FF FF)"
            return BAD
        total = 4 + buffer[start + 3]
        if total < 6:
            scan.problem = f"length {total - 4} too short"
            return BAD
        if end - start < total:
            scan.needed = total
            return NEED_MORE
        if not self.checks.sum_matches(buffer, start + 2, start + total - 1):
            scan.problem = "checksum mismatch"
            return BAD
        scan.servo_id = buffer[start + 2]
        scan.instruction = scan.error = buffer[start + 4]
        scan.first = start + 4 if status else start + 5
        scan.end = start + total - 1
        return int(total)

    def seal(self, packet: bytearray, prefix_crc: int, prefix_end: int, stuffed: bytearray) -> memoryview:
        self.checks.seal_sum(packet, prefix_end, len(packet) - 1, prefix_crc)
        return memoryview(packet)


PROTOCOLS: dict[str, Protocol] = {"dynamixel": Dynamixel2(), "feetech": Feetech()}
"""With the Python checks: the set-up's instructions and the servo model."""
_COMPILED: dict[str, Protocol] = {}


def for_the_cycle(name: str) -> Protocol:
    """The protocol ``name`` with the compiled checks where ``io/_devio.c`` was built (``io/compiled.py``:
    ``RTLOOP_PURE_PYTHON=1`` or a stale build gives the references), read when a device builds its cycle."""
    from rtloop.io.compiled import devio

    compiled = devio()
    if compiled is None:
        return PROTOCOLS[name]
    if name not in _COMPILED:
        _COMPILED[name] = type(PROTOCOLS[name])(Checks(compiled))
    return _COMPILED[name]


SIGN_BIT = np.uint16(0x8000)
MAGNITUDE_BITS = np.uint16(0x7FFF)
ZERO = np.float64(0.0)
"""Typed constants: a ufunc given a Python int or float spends microseconds deciding its type."""


class Values:
    """Float64 values ↔ one field of every servo, through a strided view on packet bytes.

    ``encode`` takes integer-valued floats (rounded and clamped already); ``decode`` gives floats.
    Sign and magnitude (``m15``) goes through preallocated contiguous temporaries (a ufunc on the
    strided, unaligned view is several times slower than one copy to or from it)."""

    def __init__(self, buffer: bytearray, first: int, stride: int, count: int, field: Field) -> None:
        kind = {("u", 1): "u1", ("u", 2): "<u2", ("u", 4): "<u4", ("s", 2): "<i2", ("s", 4): "<i4",
                ("m15", 2): "<u2"}[(field.encoding, field.width)]
        self.view = np.ndarray((count,), dtype=np.dtype(kind), buffer=buffer, offset=first, strides=(stride,))
        self.sign_magnitude = field.encoding == "m15"
        self._magnitude = np.zeros(count)
        self._bits = np.zeros(count, dtype=np.uint16)
        self._sign = np.zeros(count, dtype=np.uint16)
        self._negative = np.zeros(count, dtype=bool)

    def encode(self, raw: np.ndarray) -> None:
        if not self.sign_magnitude:
            np.copyto(self.view, raw, casting="unsafe")
            return
        bits = self._bits
        np.abs(raw, out=self._magnitude)
        np.copyto(bits, self._magnitude, casting="unsafe")
        np.less(raw, ZERO, out=self._negative)
        np.multiply(self._negative, SIGN_BIT, out=self._sign)
        np.bitwise_or(bits, self._sign, out=bits)
        np.copyto(self.view, bits)

    def decode(self, out: np.ndarray) -> None:
        if not self.sign_magnitude:
            np.copyto(out, self.view)
            return
        bits = self._bits
        np.copyto(bits, self.view)
        np.greater_equal(bits, SIGN_BIT, out=self._negative)
        np.bitwise_and(bits, MAGNITUDE_BITS, out=bits)
        np.copyto(out, bits)
        np.negative(out, out=self._magnitude)
        np.copyto(out, self._magnitude, where=self._negative)


class SyncWrite:
    """One field of every servo in one SYNC_WRITE, built once (see the module)."""

    def __init__(self, protocol: Protocol, field: Field, ids: list[int]) -> None:
        self.protocol = protocol
        params = protocol.range_params(field.address, field.width)
        params += b"".join(bytes([servo_id]) + bytes(field.width) for servo_id in ids)
        self.packet = protocol.packet(BROADCAST_ID, SYNC_WRITE, params)
        first = protocol.header_bytes + 1 + 2 * protocol.address_bytes  # the first servo's ID
        self.values = Values(self.packet, first + 1, 1 + field.width, len(ids), field)
        # what comes before the first value never changes: its CRC (or byte sum) is kept
        if isinstance(protocol, Dynamixel2):
            self.prefix_crc = crc16(self.packet, 0, first + 1)
        else:
            self.prefix_crc = sum(self.packet[2:first + 1])
        self.prefix_end = first + 1
        self.stuffed = bytearray(2 * len(self.packet))

    def seal(self) -> memoryview:
        """The packet to send, its values written through ``values`` already."""
        return self.protocol.seal(self.packet, self.prefix_crc, self.prefix_end, self.stuffed)


class SyncRead:
    """One SYNC_READ of ``width`` bytes from ``address`` of every servo, and its answers (see the module).

    The answers' bytes (error byte, then the data) land in ``clean`` at a fixed place per servo,
    whatever the stuffing on the wire, so :meth:`values` views stay valid."""

    def __init__(self, protocol: Protocol, address: int, width: int, ids: list[int]) -> None:
        self.protocol, self.address, self.width, self.ids = protocol, address, width, list(ids)
        self.request = memoryview(bytes(protocol.packet(BROADCAST_ID, SYNC_READ,
                                                        protocol.range_params(address, width) + bytes(ids))))
        self.slot = 1 + width
        self.clean = bytearray(len(ids) * self.slot)
        self.raw = bytearray(2 * len(ids) * protocol.max_status_bytes(width) + 64)  # room for a late answer's tail
        self.raw_view = memoryview(self.raw)
        self.received = np.zeros(len(ids), dtype=bool)
        self.errors = np.ndarray((len(ids),), dtype=np.uint8, buffer=self.clean, offset=0, strides=(self.slot,))
        self.index_of = [-1] * 256
        for index, servo_id in enumerate(ids):
            self.index_of[servo_id] = index
        self.take: Any = protocol.checks.take_answers  # the loop below in C, where built
        self.dynamixel = isinstance(protocol, Dynamixel2)
        self.index_by_id = np.array(self.index_of, dtype=np.int16)
        self.take_state = np.zeros(4, dtype=np.int64)  # (start, count, needed, a bad packet seen), C's
        self.scan = Scan()
        self.problem = ""
        """Why the last exchange stopped short (a bad packet, a timeout), or ''."""

    def values(self, field: Field) -> Values:
        return Values(self.clean, 1 + field.address - self.address, self.slot, len(self.ids), field)

    def exchange(self, line: Line, timeout_ns: int) -> int:
        """Send the request, take the answers that come within ``timeout_ns``: how many servos answered."""
        line.send(self.request)
        return self.collect(line, timeout_ns)

    def collect(self, line: Line, timeout_ns: int) -> int:
        if self.take is not None:
            return self._collect_compiled(line, timeout_ns)
        protocol = self.protocol  # (one name a line: a tuple here would be kept by the interpreter's free list)
        scan = self.scan
        raw = self.raw
        received = self.received
        received[:] = False
        self.problem = ""
        deadline_ns = time.monotonic_ns() + timeout_ns
        got = start = count = 0
        wanted = len(self.ids)
        while count < wanted:
            size = protocol.scan(raw, start, got, scan, True)
            if size == NEED_MORE:
                if start + scan.needed > len(raw):
                    self.problem = "answers longer than expected"
                    return count
                # (asked even when the time is up: what is there already counts, and a model in
                # process answers whatever the host's clock says, so a simulation never times out)
                came = line.receive(self.raw_view[got:], deadline_ns - time.monotonic_ns())
                if came == 0:
                    self.problem = "no answer within timeout_ms" + (" (and a bad packet)" if self.problem else "")
                    return count
                got += came
                continue
            if size == BAD:  # the tail of a late answer the flush before this request missed, or noise:
                self.problem = "bad packet"  # look for the next header (else every cycle after would start so)
                start += 1
                continue
            index = self.index_of[scan.servo_id]
            if index >= 0 and not received[index] and \
                    protocol.copy_params(raw, scan, self.clean, index * self.slot, self.slot):
                received[index] = True
                count += 1
            start += size
        return count


    def _collect_compiled(self, line: Line, timeout_ns: int) -> int:
        """:meth:`collect` with its scanning loop in C (``io/devio_c/servo.c`` servo_take_answers): the same
        answers taken, the same counts and problems."""
        take = self.take
        raw = self.raw
        state = self.take_state
        state.fill(0)
        self.received[:] = False
        deadline_ns = time.monotonic_ns() + timeout_ns
        got = 0
        wanted = len(self.ids)
        while True:
            verdict = take(self.dynamixel, raw, got, wanted, self.clean, self.slot, self.index_by_id, self.received,
                           state)
            if verdict == 0:
                self.problem = "bad packet" if state[3] else ""
                break
            if verdict == 2:
                self.problem = "answers longer than expected"
                break
            came = line.receive(self.raw_view[got:], deadline_ns - time.monotonic_ns())
            if came == 0:
                self.problem = "no answer within timeout_ms" + (" (and a bad packet)" if state[3] else "")
                break
            got += came
        return int(state[1])


def request(protocol: Protocol, line: Line, servo_id: int, instruction: int, params: bytes,
            timeout_ns: int) -> tuple[int, bytes] | None:
    """One instruction and its status (set-up, outside the loop): (error byte, parameters), or None."""
    line.flush_input()
    line.send(protocol.packet(servo_id, instruction, params))
    buffer = bytearray(512)
    view = memoryview(buffer)
    scan = Scan()
    got = start = 0
    deadline_ns = time.monotonic_ns() + timeout_ns
    while True:
        size = protocol.scan(buffer, start, got, scan, True)
        if size == NEED_MORE:
            if start + scan.needed > len(buffer):
                return None
            came = line.receive(view[got:], deadline_ns - time.monotonic_ns())
            if came == 0:
                return None
            got += came
            continue
        if size == BAD:
            return None
        if scan.servo_id == servo_id:
            body = bytes(buffer[scan.first:scan.end])
            if isinstance(protocol, Dynamixel2):
                body = destuff(body)
            return body[0], body[1:]
        start += size  # another servo's answer (an echo on a half-duplex adapter): pass over it
