"""The slave information interface (SII): the EEPROM an EtherCAT slave describes itself with.

:func:`build_sii` writes the image an emulated slave serves (identity words, then categories:
strings 10, general 30, FMMU 40, SyncM 41, TXPDO 50, RXPDO 51, end 0xFFFF, as ETG.2010 lays them
out); :func:`parse_sii` reads one back, as the master does to check a slave against the app file.
Word addresses, little-endian words.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass, field

from rtloop.io.drives.pdo import PdoEntry

__all__ = ["Identity", "SiiInfo", "SyncManagerSpec", "build_sii", "parse_sii"]

VENDOR_WORD, PRODUCT_WORD, REVISION_WORD, SERIAL_WORD = 0x08, 0x0A, 0x0C, 0x0E
MAILBOX_WORD = 0x18
FIRST_CATEGORY_WORD = 0x40
CAT_STRINGS, CAT_GENERAL, CAT_FMMU, CAT_SYNCM, CAT_TXPDO, CAT_RXPDO, CAT_DC, CAT_END = 10, 30, 40, 41, 50, 51, 60, \
    0xFFFF
DC_ASSIGN_ACTIVATE_SYNC0 = 0x0300
"""A DC operation mode's AssignActivate: cyclic operation and SYNC0 (register 0x0980-0x0981)."""


@dataclass(frozen=True, slots=True)
class Identity:
    vendor: int
    product: int
    revision: int
    serial: int = 0

    def describe(self) -> str:
        return f"vendor 0x{self.vendor:08X}, product 0x{self.product:08X}, revision 0x{self.revision:08X}"


@dataclass(frozen=True, slots=True)
class SyncManagerSpec:
    start: int
    length: int
    control: int
    enable: int
    kind: int
    """1 mailbox out, 2 mailbox in, 3 process data outputs, 4 process data inputs."""


@dataclass
class SiiInfo:
    identity: Identity
    name: str = ""
    sync_managers: list[SyncManagerSpec] = field(default_factory=list)
    fmmu_functions: list[int] = field(default_factory=list)
    rxpdo: list[PdoEntry] = field(default_factory=list)
    """Entries of the RxPDOs assigned to a sync manager, in order (master → slave)."""
    txpdo: list[PdoEntry] = field(default_factory=list)
    has_mailbox: bool = False
    dc_assign_activate: int = 0
    """The first DC operation mode's AssignActivate (category 60); 0: the slave describes no DC mode."""


def _category(kind: int, data: bytes) -> bytes:
    if len(data) % 2:
        data += b"\0"
    return struct.pack("<HH", kind, len(data) // 2) + data


def _pdo_category(pdo_index: int, sync_manager: int, entries: tuple[PdoEntry, ...]) -> bytes:
    data = struct.pack("<HBBBBH", pdo_index, len(entries), sync_manager, 0, 0, 0)
    for entry in entries:
        data += struct.pack("<HBBBBH", entry.index, entry.subindex, 0, entry.data_type, entry.bits, 0)
    return data


def build_sii(identity: Identity, name: str, rx: tuple[PdoEntry, ...], tx: tuple[PdoEntry, ...],
              outputs_at: int = 0x1000, inputs_at: int = 0x1200, dc: bool = False) -> bytes:
    """The EEPROM of a CiA 402 slave without a mailbox: its process data on SM0 (outputs) and SM1
    (inputs), FMMU0 outputs and FMMU1 inputs; with ``dc``, a DC category with one operation mode
    (SYNC0: cycle time 0, that is the master's, no shift)."""
    words = bytearray(FIRST_CATEGORY_WORD * 2)
    struct.pack_into("<IIII", words, VENDOR_WORD * 2, identity.vendor, identity.product, identity.revision,
                     identity.serial)
    struct.pack_into("<HH", words, 0x3E * 2, 1, 1)  # EEPROM size (KiBit - 1), version
    out_bytes = sum(e.bits for e in rx) // 8
    in_bytes = sum(e.bits for e in tx) // 8
    text = name.encode()[:255]
    general = bytearray(32)
    general[3] = 1  # the name is string 1
    general[0x0C] = 0  # flags
    syncm = (struct.pack("<HHBBBB", outputs_at, out_bytes, 0x64, 0, 1, 3)
             + struct.pack("<HHBBBB", inputs_at, in_bytes, 0x20, 0, 1, 4))
    image = (bytes(words) + _category(CAT_STRINGS, bytes([1, len(text)]) + text)
             + _category(CAT_GENERAL, bytes(general)) + _category(CAT_FMMU, bytes([1, 2]))
             + _category(CAT_SYNCM, syncm) + _category(CAT_TXPDO, _pdo_category(0x1A00, 1, tx))
             + _category(CAT_RXPDO, _pdo_category(0x1600, 0, rx))
             + (_category(CAT_DC, struct.pack("<IIIhHhBB4x", 0, 0, 0, 0, DC_ASSIGN_ACTIVATE_SYNC0, 0, 0, 0))
                if dc else b"")
             + struct.pack("<HH", CAT_END, 0))
    return image + b"\xff" * (-len(image) % 8)


def parse_sii(read: Callable[[int], bytes], limit_words: int = 4096) -> SiiInfo:
    """Read a slave's SII through ``read(word_address) -> bytes`` (4 or 8 bytes from that word)."""
    cache: dict[int, int] = {}

    def word(address: int) -> int:
        if address not in cache:
            data = read(address)
            for i in range(len(data) // 2):
                cache[address + i] = data[2 * i] | data[2 * i + 1] << 8
        return cache[address]

    def block(address: int, count: int) -> bytes:
        return b"".join(struct.pack("<H", word(address + i)) for i in range(count))

    identity = Identity(*struct.unpack("<IIII", block(VENDOR_WORD, 8)))
    info = SiiInfo(identity, has_mailbox=word(MAILBOX_WORD + 1) > 0)
    strings: list[str] = []
    name_index = 0
    at = FIRST_CATEGORY_WORD
    while at < limit_words:
        kind, length = word(at), word(at + 1)
        if kind == CAT_END or kind == 0xFFFF:
            break
        data = block(at + 2, length)
        if kind == CAT_STRINGS and data:
            pos = 1
            for _ in range(data[0]):
                size = data[pos]
                strings.append(data[pos + 1:pos + 1 + size].decode(errors="replace"))
                pos += 1 + size
        elif kind == CAT_GENERAL and len(data) > 3:
            name_index = data[3]
        elif kind == CAT_FMMU:
            info.fmmu_functions = [b for b in data if b not in (0, 0xFF)]
        elif kind == CAT_SYNCM:
            for pos in range(0, len(data) - 7, 8):
                start, size, control, _status, enable, sm_kind = struct.unpack_from("<HHBBBB", data, pos)
                info.sync_managers.append(SyncManagerSpec(start, size, control, enable, sm_kind))
        elif kind == CAT_DC and len(data) >= 24 and not info.dc_assign_activate:
            info.dc_assign_activate = struct.unpack_from("<H", data, 14)[0]
        elif kind in (CAT_TXPDO, CAT_RXPDO):
            target = info.txpdo if kind == CAT_TXPDO else info.rxpdo
            pos = 0
            while pos + 8 <= len(data):
                _index, count, sync_manager = struct.unpack_from("<HBB", data, pos)
                pos += 8
                for _ in range(count):
                    index, subindex, _name, data_type, bits = struct.unpack_from("<HBBBB", data, pos)
                    pos += 8
                    if sync_manager != 0xFF:  # a PDO not assigned to a sync manager is not exchanged
                        target.append(PdoEntry(index, subindex, bits, data_type))
        at += 2 + length
    if 0 < name_index <= len(strings):
        info.name = strings[name_index - 1]
    return info
