"""CANopen (CiA 301) on the wire, the few frames a CiA 402 drive needs: NMT, SYNC, expedited SDO,
PDOs, heartbeat and EMCY. Shared by the drive device (``io/drives/canopen.py``) and the emulated
node (``io/drives/canopen_node.py``); plain functions on ints and bytes, no socket.

COB-IDs of the predefined connection set (node ``n``, 1..127)::

    NMT 0x000   SYNC 0x080   EMCY 0x080+n   TPDO1..4 0x180/0x280/0x380/0x480+n
    RPDO1..4 0x200/0x300/0x400/0x500+n   SDO request 0x600+n, answer 0x580+n   heartbeat 0x700+n

A wire frame here is SocketCAN's classic ``struct can_frame`` (16 bytes: id, length, 3 pad, 8 data).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

from rtloop.io.drives.pdo import OBJECTS, PdoLayout

__all__ = ["NMT_PRE_OPERATIONAL", "NMT_RESET_COMMUNICATION", "NMT_START", "NMT_STOP", "SYNC_ID", "SdoAbort",
           "emcy_id", "heartbeat_id", "mapping_writes", "pdo_chunks", "rpdo_id", "sdo_answer", "sdo_answer_id",
           "sdo_download", "sdo_request_id", "sdo_upload", "tpdo_id", "wire_frame"]

WIRE = struct.Struct("<IB3x8s")
"""SocketCAN's classic frame: 32-bit id, data length, padding, 8 data bytes."""
DATA_AT = 8
SYNC_ID = 0x080
NMT_START, NMT_STOP, NMT_PRE_OPERATIONAL, NMT_RESET_NODE, NMT_RESET_COMMUNICATION = 0x01, 0x02, 0x80, 0x81, 0x82
HEARTBEAT_STATES = {0x00: "boot-up", 0x04: "stopped", 0x05: "operational", 0x7F: "pre-operational"}
MAX_PDOS = 4
"""PDOs per direction in the predefined connection set."""

EMCY_NAMES = {0x0000: "error reset or no error", 0x1000: "generic error", 0x2300: "output current",
              0x3200: "DC link voltage", 0x4200: "device temperature", 0x5530: "power stage (drive hardware)",
              0x8130: "heartbeat or life guard error", 0x8611: "following error", 0x8700: "sync controller error"}
"""CiA 301/402 emergency error codes a fault names (any other is given by its number)."""


def emcy_id(node: int) -> int:
    return 0x080 + node


def heartbeat_id(node: int) -> int:
    return 0x700 + node


def sdo_request_id(node: int) -> int:
    return 0x600 + node


def sdo_answer_id(node: int) -> int:
    return 0x580 + node


def tpdo_id(node: int, number: int) -> int:
    """TPDO ``number`` (0..3) of ``node``."""
    return 0x180 + 0x100 * number + node


def rpdo_id(node: int, number: int) -> int:
    return 0x200 + 0x100 * number + node


def wire_frame(can_id: int, data: bytes | bytearray = b"", length: int | None = None) -> bytearray:
    """A SocketCAN wire frame (allocated: outside the loop, or once and rewritten)."""
    size = len(data) if length is None else length
    return bytearray(WIRE.pack(can_id, size, bytes(data)))


def emcy_name(code: int) -> str:
    return EMCY_NAMES.get(code) or EMCY_NAMES.get(code & 0xFF00, "") or "unknown to rtloop"


# --- expedited SDO (CiA 301 §7.2.4.3) ------------------------------------------------------------------

class SdoAbort(Exception):
    """The node answered an SDO with an abort: ``code`` (0x06020000: the object does not exist, ...)."""

    def __init__(self, index: int, subindex: int, code: int) -> None:
        self.index, self.subindex, self.code = index, subindex, code
        super().__init__(f"SDO 0x{index:04X}:{subindex} aborted with code 0x{code:08X}")


def sdo_upload(index: int, subindex: int) -> bytes:
    """The request to read ``index:subindex`` (initiate upload)."""
    return struct.pack("<BHB4x", 0x40, index, subindex)


def sdo_download(index: int, subindex: int, value: int, size: int) -> bytes:
    """The request to write ``value`` (``size`` 1, 2 or 4 bytes, little-endian) expedited."""
    command = 0x23 | (4 - size) << 2  # expedited, size indicated, n = bytes without data
    data = (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")
    return struct.pack("<BHB", command, index, subindex) + data.ljust(4, b"\0")


def sdo_answer(data: bytes | bytearray, index: int, subindex: int) -> int | None:
    """The value of an answer to a request on ``index:subindex`` (an upload's value, 0 for a download's
    confirmation); None when the answer is for another object; :class:`SdoAbort` on an abort."""
    if len(data) < 8:
        return None
    command, got_index, got_sub = struct.unpack_from("<BHB", data, 0)
    if (got_index, got_sub) != (index, subindex):
        return None
    if command == 0x80:
        raise SdoAbort(index, subindex, struct.unpack_from("<I", data, 4)[0])
    if command == 0x60:
        return 0
    if command & 0xE3 == 0x43:  # upload answer, expedited, size indicated
        size = 4 - (command >> 2 & 3)
        return int.from_bytes(bytes(data[4:4 + size]), "little")
    if command & 0xE2 == 0x42:  # expedited, size not indicated: all four bytes
        return int.from_bytes(bytes(data[4:8]), "little")
    return None


# --- PDO mapping -------------------------------------------------------------------------------------

def pdo_chunks(layout: PdoLayout) -> list[tuple[int, int, tuple[int, ...]]]:
    """The layout's objects split into PDOs of at most 8 bytes, in order: (byte offset, length,
    objects) per PDO. ValueError when they need more than four PDOs."""
    chunks: list[tuple[int, int, tuple[int, ...]]] = []
    start = length = 0
    objects: list[int] = []
    for index in layout.objects:
        size = OBJECTS[index].bits // 8
        if length + size > 8:
            chunks.append((start, length, tuple(objects)))
            start, length, objects = start + length, 0, []
        objects.append(index)
        length += size
    if objects:
        chunks.append((start, length, tuple(objects)))
    if len(chunks) > MAX_PDOS:
        raise ValueError(f"the objects take {layout.size} bytes: {len(chunks)} PDOs of 8 bytes, a node has "
                         f"{MAX_PDOS}; map fewer objects")
    return chunks


def mapping_writes(node: int, rx: PdoLayout, tx: PdoLayout) -> list[tuple[int, int, int, int]]:
    """The SDO writes (index, subindex, value, size) that map ``rx`` into the node's RPDOs and ``tx``
    into its TPDOs, each synchronous (transmission type 1: taken and sent at every SYNC), and switch
    the PDOs rtloop does not use off. CiA 301's order: invalidate the PDO (COB-ID bit 31), clear its
    mapping (sub 0 = 0), write the entries, set the count, then make the PDO valid again."""
    writes: list[tuple[int, int, int, int]] = []
    for layout, comm, mapping, cob in ((rx, 0x1400, 0x1600, rpdo_id), (tx, 0x1800, 0x1A00, tpdo_id)):
        chunks = pdo_chunks(layout)
        for number in range(MAX_PDOS):
            cob_id = cob(node, number)
            writes.append((comm + number, 1, cob_id | 1 << 31, 4))
            if number >= len(chunks):
                continue
            writes.append((comm + number, 2, 1, 1))
            writes.append((mapping + number, 0, 0, 1))
            objects = chunks[number][2]
            for sub, index in enumerate(objects, start=1):
                writes.append((mapping + number, sub, index << 16 | OBJECTS[index].bits, 4))
            writes.append((mapping + number, 0, len(objects), 1))
            writes.append((comm + number, 1, cob_id, 4))
    return writes


def objects_in(mapping_entries: Sequence[int]) -> tuple[int, ...]:
    """The object indices of mapping entries (``index << 16 | subindex << 8 | bits``)."""
    return tuple(entry >> 16 for entry in mapping_entries)
