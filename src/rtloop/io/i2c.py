"""I2C devices: SMBus register reads and writes every cycle (``smbus2``).

    [devices.imu]
    kind = "i2c"
    bus = 1                          # /dev/i2c-1
    address = 0x68
    reads = [{ name = "gyro_z", register = 0x47, type = "i16", byte_order = "big", scale = 0.0076 }]
    writes = [{ name = "fan", register = 0x10, type = "u8", scale = 0.01 }]

``u8``/``i8`` registers move with SMBus "byte data", ``u16``/``i16`` with "word data" (SMBus
sends the low byte first; ``byte_order = "big"`` for chips that put the high byte first).
Values scale as in every frame: ``value = raw * scale + offset``, rounded and saturated on
the way out. ``smbus2`` opens the bus, sets the address and gives the kernel's structs; each
register then has its ``I2C_SMBUS`` message built once (smbus2's ``read_byte_data`` builds a
new one on every call), so a cycle is one ioctl per register and nothing else.
"""

from __future__ import annotations

import os
from typing import Any, ClassVar

from rtloop.errors import DeviceError
from rtloop.io.bytelayout import ByteLayout, Field, FloatView, LayoutError, field_from_table
from rtloop.io.device import Device, FloatVector, Setting
from rtloop.io.kernel import (
    I2C_FUNC_SMBUS_READ_BYTE_DATA,
    I2C_FUNC_SMBUS_READ_WORD_DATA,
    I2C_FUNC_SMBUS_WRITE_BYTE_DATA,
    I2C_FUNC_SMBUS_WRITE_WORD_DATA,
    I2C_SMBUS,
    I2C_SMBUS_BYTE_DATA,
    I2C_SMBUS_READ,
    I2C_SMBUS_WORD_DATA,
    I2C_SMBUS_WRITE,
)
from rtloop.linux import rt

__all__ = ["I2cDevice"]

REGISTER_TYPES = ("u8", "i8", "u16", "i16")
FUNCTIONS = {("read", False): I2C_FUNC_SMBUS_READ_BYTE_DATA, ("read", True): I2C_FUNC_SMBUS_READ_WORD_DATA,
             ("write", False): I2C_FUNC_SMBUS_WRITE_BYTE_DATA, ("write", True): I2C_FUNC_SMBUS_WRITE_WORD_DATA}
"""The adapter functionality (I2C_FUNCS bits) each kind of register transfer needs."""


def _registers(value: list[Any]) -> str | None:
    if not all(isinstance(item, dict) for item in value):
        return "expected an array of tables ({ name, register, type, scale, offset })"
    return None


def register_from_table(table: dict[str, Any], where: str) -> tuple[int, Field]:
    """(register number, its value as a field over the SMBus data bytes)."""
    register = table.get("register")
    if not isinstance(register, int) or isinstance(register, bool) or not 0 <= register <= 0xFF:
        raise LayoutError(f"{where}.register: expected a register number 0..0xFF, got {register!r}")
    kind = table.get("type", "u8")
    if kind not in REGISTER_TYPES:
        raise LayoutError(f"{where}.type: an SMBus register holds one of {', '.join(REGISTER_TYPES)}, got {kind!r}")
    rest = {key: value for key, value in table.items() if key != "register"}
    return register, field_from_table({**rest, "start_byte": 0, "type": kind}, where)


def _check_one_write_each(writes: list[tuple[int, Field]]) -> None:
    """Two writes of one register each cycle: the second would undo the first, every cycle. (Reading
    back a register written is allowed: a chip's readback is a check.)"""
    first: dict[int, int] = {}
    for index, (register, _) in enumerate(writes):
        if register in first:
            earlier = first[register]
            raise LayoutError(f"writes[{index}].register: 0x{register:02X} is also written by writes[{earlier}] "
                              f"({writes[earlier][1].name!r}); a register is written once a cycle")
        first[register] = index


class I2cDevice(Device):
    """Registers of one I2C chip, read and written with SMBus transfers every cycle."""

    kind: ClassVar[str] = "i2c"
    settings: ClassVar[dict[str, Setting]] = {
        "bus": Setting(int, doc="the I2C bus number N of /dev/i2c-N: bus = 1",
                       check=lambda v: None if 0 <= v < 1 << 20 else f"expected a bus number, got {v!r}"),
        "address": Setting(int, doc="the chip's 7-bit address",
                           check=lambda v: None if 0x03 <= v <= 0x77 else f"expected 0x03..0x77, got {v!r}"),
        "reads": Setting(list, [], "registers read every cycle", _registers),
        "writes": Setting(list, [], "registers written every cycle", _registers),
    }

    def __init__(self, name: str, **settings: Any) -> None:
        super().__init__(name, **settings)
        self.bus: int = settings["bus"]
        self.address: int = settings["address"]
        try:
            self.reads = [register_from_table(t, f"reads[{i}]") for i, t in enumerate(settings["reads"])]
            self.writes = [register_from_table(t, f"writes[{i}]") for i, t in enumerate(settings["writes"])]
            _check_one_write_each(self.writes)
        except LayoutError as error:
            key, _, problem = str(error).partition(": ")
            raise DeviceError(name, "", key, problem) from None
        self.input_names = tuple(field.name for _, field in self.writes)
        self.output_names = tuple(field.name for _, field in self.reads)
        self.n_inputs, self.n_outputs = len(self.writes), len(self.reads)
        self.path = f"/dev/i2c-{self.bus}"
        self._bus: Any = None
        self._u, self._y = FloatView(), FloatView()

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_bus": None, "_messages": None}

    # --- supervisor ---------------------------------------------------------------------------
    def check(self) -> None:
        self._open().close()

    def _open(self) -> Any:
        try:
            from smbus2 import SMBus
        except ImportError:
            raise DeviceError(self.name, "", "kind", "I2C needs smbus2: pip install smbus2 (or rtloop[i2c])") from None
        if not os.path.exists(self.path):
            buses = sorted(n for n in os.listdir("/dev") if n.startswith("i2c-"))
            found = f"I2C buses here: {', '.join(buses)}" if buses else "no /dev/i2c-N here (modprobe i2c-dev?)"
            raise DeviceError(self.name, "", "bus", f"no I2C bus {self.path} ({found})")
        try:
            bus = SMBus(self.bus)
        except PermissionError:
            raise DeviceError(self.name, "", "bus", f"no permission to open {self.path} (run as root, or add this "
                              "user to the group owning it, often 'i2c')") from None
        except OSError as error:
            raise DeviceError(self.name, "", "bus", f"cannot open {self.path}: {error.strerror}") from None
        try:
            needed = self._needed_functions()
            missing = needed & ~bus.funcs
            if missing:
                raise DeviceError(self.name, "", "bus", f"{self.path} cannot do the SMBus transfers declared "
                                  f"(functionality mask lacks 0x{missing:08X})")
            try:
                bus._set_address(self.address)  # type: ignore[attr-defined]  # private in smbus2's stubs; I2C_SLAVE: refused (EBUSY) when a kernel driver owns the chip
            except OSError as error:
                raise DeviceError(self.name, "", "address", f"0x{self.address:02X} on {self.path}: {error.strerror}"
                                  + (" (a kernel driver owns it)" if error.errno == 16 else "")) from None
        except BaseException:
            bus.close()
            raise
        return bus

    def _needed_functions(self) -> int:
        needed = 0
        for side, registers in (("read", self.reads), ("write", self.writes)):
            for _register, field in registers:
                needed |= FUNCTIONS[side, field.size_bytes == 2]
        return needed

    # --- task process ---------------------------------------------------------------------------
    def configure(self) -> None:
        from smbus2.smbus2 import i2c_smbus_ioctl_data

        self._bus = self._open()
        self._fd = self._bus.fd
        # One message per register, its data union allocated once; the field packs into the union's bytes.
        self._read_plan = [self._message(i2c_smbus_ioctl_data, I2C_SMBUS_READ, register, field, f"reads[{i}]")
                           for i, (register, field) in enumerate(self.reads)]
        self._write_plan = [self._message(i2c_smbus_ioctl_data, I2C_SMBUS_WRITE, register, field, f"writes[{i}]")
                            for i, (register, field) in enumerate(self.writes)]
        # a chip that does not answer: refuse to start, with the reason, rather than fault at cycle 0
        for message, _data, _layout in self._read_plan:
            try:
                rt.ioctl(self._fd, I2C_SMBUS, message, "I2C_SMBUS")
            except OSError as error:
                self.close()
                raise DeviceError(self.name, "", "address", f"no answer from 0x{self.address:02X} on {self.path} "
                                  f"(register 0x{message.command:02X}): {error.strerror}") from None

    def _message(self, cls: Any, direction: int, register: int, field: Field, where: str) -> tuple[Any, Any, Any]:
        message = cls.create(read_write=direction, command=register,
                             size=I2C_SMBUS_WORD_DATA if field.size_bytes == 2 else I2C_SMBUS_BYTE_DATA)
        data = message.data.contents  # union i2c_smbus_data: byte, word, block[34]
        return message, data, ByteLayout([field], 2, where)

    def write(self, u: FloatVector) -> None:
        fd, u = self._fd, self._u.of(u)
        for index, (message, data, layout) in enumerate(self._write_plan):
            layout.pack_into(data, 0, u, index)
            rt.ioctl(fd, I2C_SMBUS, message, "I2C_SMBUS")

    def read(self, y: FloatVector) -> None:
        fd, y = self._fd, self._y.of(y)
        for index, (message, data, layout) in enumerate(self._read_plan):
            rt.ioctl(fd, I2C_SMBUS, message, "I2C_SMBUS")
            layout.unpack_from(data, 0, y, index)

    def close(self) -> None:
        if self._bus is not None:
            self._bus.close()
            self._bus = None
