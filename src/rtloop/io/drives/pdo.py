"""Process data objects of a CiA 402 drive: which objects a mapping carries, where, in what type.

A mapping is a list of object indices in order (``0x6040`` controlword, ``0x607A`` target
position, ...), as an app file names them (``rxpdo = ["0x6040", "0x6060", "0x607A"]``) or an ESI
file or the slave's SII EEPROM describes them. :class:`PdoLayout` packs and unpacks one slave's
part of the process image with one ``struct.Struct`` built once.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from rtloop.io.drives import cia402

__all__ = ["DEFAULT_RXPDO", "DEFAULT_TXPDO", "OBJECTS", "PdoEntry", "PdoLayout", "parse_object"]


@dataclass(frozen=True, slots=True)
class ObjectInfo:
    name: str
    code: str
    """``struct`` code (little-endian on the wire)."""
    data_type: int
    """CoE data type: 2 INTEGER8, 3 INTEGER16, 4 INTEGER32, 6 UNSIGNED16."""
    direction: str
    """``rx`` (master → drive, an output) or ``tx`` (drive → master, an input)."""

    @property
    def bits(self) -> int:
        return struct.calcsize("<" + self.code) * 8


OBJECTS: dict[int, ObjectInfo] = {
    cia402.CONTROLWORD: ObjectInfo("controlword", "H", 6, "rx"),
    cia402.MODES_OF_OPERATION: ObjectInfo("modes of operation", "b", 2, "rx"),
    cia402.TARGET_POSITION: ObjectInfo("target position", "i", 4, "rx"),
    cia402.TARGET_VELOCITY: ObjectInfo("target velocity", "i", 4, "rx"),
    cia402.TARGET_TORQUE: ObjectInfo("target torque", "h", 3, "rx"),
    cia402.STATUSWORD: ObjectInfo("statusword", "H", 6, "tx"),
    cia402.MODES_DISPLAY: ObjectInfo("modes of operation display", "b", 2, "tx"),
    cia402.POSITION_ACTUAL: ObjectInfo("position actual value", "i", 4, "tx"),
    cia402.VELOCITY_ACTUAL: ObjectInfo("velocity actual value", "i", 4, "tx"),
    cia402.TORQUE_ACTUAL: ObjectInfo("torque actual value", "h", 3, "tx"),
    cia402.FOLLOWING_ERROR_ACTUAL: ObjectInfo("following error actual value", "i", 4, "tx"),
    cia402.ERROR_CODE: ObjectInfo("error code", "H", 6, "tx"),
}
"""The CiA 402 objects rtloop reads and writes in process data."""

DEFAULT_RXPDO = (cia402.CONTROLWORD, cia402.MODES_OF_OPERATION, cia402.TARGET_POSITION, cia402.TARGET_VELOCITY,
                 cia402.TARGET_TORQUE)
DEFAULT_TXPDO = (cia402.STATUSWORD, cia402.MODES_DISPLAY, cia402.POSITION_ACTUAL, cia402.VELOCITY_ACTUAL,
                 cia402.TORQUE_ACTUAL, cia402.FOLLOWING_ERROR_ACTUAL, cia402.ERROR_CODE)
"""The mapping an app file gets when it names none (and the emulated drive's)."""


@dataclass(frozen=True, slots=True)
class PdoEntry:
    """One entry of a mapping as a slave describes it (SII or ESI)."""

    index: int
    subindex: int
    bits: int
    data_type: int = 0


def parse_object(text: object) -> int:
    """``"0x6040"`` (or ``0x6040`` as a TOML integer, or ``"0x6040:0"``) → 0x6040; ValueError says why."""
    if isinstance(text, int) and not isinstance(text, bool):
        index = text
    elif isinstance(text, str):
        head = text.strip().partition(":")[0]
        try:
            index = int(head, 0)
        except ValueError:
            raise ValueError(f"{text!r} is not an object index such as '0x6040'") from None
    else:
        raise ValueError(f"{text!r} is not an object index such as '0x6040'")
    if index not in OBJECTS:
        known = ", ".join(f"0x{i:04X} ({info.name})" for i, info in OBJECTS.items())
        raise ValueError(f"object 0x{index:04X} is not one rtloop maps; known: {known}")
    return index


class PdoLayout:
    """One slave's outputs (``rx``) or inputs (``tx``): the objects in order, packed in one go."""

    def __init__(self, objects: tuple[int, ...]) -> None:
        self.objects = objects
        self.struct = struct.Struct("<" + "".join(OBJECTS[index].code for index in objects))
        self.size = self.struct.size
        self.offsets: dict[int, int] = {}
        at = 0
        for index in objects:
            self.offsets[index] = at
            at += OBJECTS[index].bits // 8
        self.position = {index: i for i, index in enumerate(objects)}
        """Object → its place among the values :meth:`struct.unpack_from` gives."""

    def __reduce__(self) -> tuple[type, tuple[tuple[int, ...]]]:
        return PdoLayout, (self.objects,)  # a struct.Struct does not pickle; it is rebuilt from the objects

    def entries(self) -> tuple[PdoEntry, ...]:
        return tuple(PdoEntry(index, 0, OBJECTS[index].bits, OBJECTS[index].data_type) for index in self.objects)

    def __contains__(self, index: int) -> bool:
        return index in self.offsets
