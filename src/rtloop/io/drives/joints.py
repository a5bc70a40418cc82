"""A drive device's joints as its app file declares them, checked before anything starts.

    joints = [
      { name = "pan", vendor = 0xA7E, product = 0x402402, revision = 0x10000, mode = "csp",
        counts_per_rev = 4096, gear_ratio = 19.0, direction = 1 },
    ]

One table per drive, in bus order. ``rxpdo``/``txpdo`` name the objects of its mapping in order
(default: :data:`~rtloop.io.drives.pdo.DEFAULT_RXPDO` / ``DEFAULT_TXPDO``), or ``esi`` names the
drive's ESI XML file, whose identity and first RxPDO/TxPDO give them, and whether it has
distributed clocks (a ``Dc/OpMode`` with a non-zero ``AssignActivate``). ``dc`` (EtherCAT) runs the
drive on distributed clocks (``true``) or free on the frames (``false``); by default on DC where the
slave has them (its ESI, when given, and its SII). ``drive`` holds the
emulated drive's parameters (:class:`~rtloop.io.drives.drive_model.DriveParameters`: the twin's
and the emulator's motor, load and loops).
"""

from __future__ import annotations

import dataclasses
import math
import stat
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.parsers import expat

from rtloop.io.device import CommandLimit, Setting, positive
from rtloop.io.drives import cia402
from rtloop.io.drives.cia402 import MODES, JointScale
from rtloop.io.drives.drive_model import DriveParameters
from rtloop.io.drives.pdo import DEFAULT_RXPDO, DEFAULT_TXPDO, OBJECTS, PdoLayout, parse_object
from rtloop.io.drives.sii import Identity

__all__ = ["QUICK_STOP_TIMEOUT", "JointConfig", "JointError", "joint_from_table", "joint_limits", "joint_tables_check",
           "read_description_file"]

JOINT_KEYS = {"name", "vendor", "product", "revision", "mode", "modes", "counts_per_rev", "gear_ratio", "direction",
              "rated_torque_Nm", "rxpdo", "txpdo", "esi", "drive", "dc"}


QUICK_STOP_TIMEOUT = Setting(float, 2.0, "how long the safe transition may take (quick stop, then disable) before "
                             "rtloop gives up on it", positive, at_most=60.0)
"""A drive device's ``quick_stop_timeout_s`` setting (EtherCAT and CANopen alike)."""


def joint_tables_check(keys: str) -> Any:
    """A ``joints`` setting's check: a non-empty list of tables (``keys`` shows what goes in one)."""

    def check(value: list[Any]) -> str | None:
        if not value or not all(isinstance(item, dict) for item in value):
            return f"expected one table per drive, in bus order: [{{ {keys}, ... }}]"
        return None

    return check


def joint_limits(joints: tuple[JointConfig, ...], input_names: tuple[str, ...]) -> dict[str, CommandLimit]:
    """A drive device's default command limits (its ``input_names``): a joint's mode command within
    CSP..CST, starting in its first mode; the set points wide open (the app's limits say what the
    machine allows)."""
    first_modes = {f"{joint.name}_target_mode": joint.modes[0] for joint in joints}
    return {name: CommandLimit(8, 10, first_modes[name]) if name in first_modes else CommandLimit(-1e6, 1e6, 0.0)
            for name in input_names}


class JointError(ValueError):
    """A joint's table is wrong: ``key`` (``joints[0].mode``) and the problem."""

    def __init__(self, key: str, problem: str) -> None:
        self.key, self.problem = key, problem
        super().__init__(f"{key}: {problem}")


@dataclass(frozen=True)
class JointConfig:
    name: str
    slave: int
    """Its position on the bus, from 1."""
    identity: Identity
    modes: tuple[int, ...]
    """Modes it may be driven in (0x6060 codes); the first is the one it starts in."""
    scale: JointScale
    rx: PdoLayout
    tx: PdoLayout
    drive: DriveParameters
    dc: bool | None = None
    """Run on distributed clocks (True), free on the frames (False), or where the slave has them (None)."""
    esi_dc: bool | None = None
    """Whether the joint's ESI file describes a DC operation mode (None: no ESI file given)."""

    @property
    def mode_command(self) -> bool:
        """Whether the task chooses the mode at each release (more than one mode declared)."""
        return len(self.modes) > 1


def _number(table: dict[str, Any], key: str, where: str, default: float | None = None) -> float:
    value = table.get(key, default)
    if value is None:
        raise JointError(f"{where}.{key}", "missing")
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise JointError(f"{where}.{key}", f"expected a number, got {value!r}")
    return float(value)


def _id(table: dict[str, Any], key: str, where: str, esi: Identity | None) -> int:
    if key not in table:
        if esi is not None:
            return int(getattr(esi, key))
        raise JointError(f"{where}.{key}", f"missing: the drive's {key} (as in its ESI file; "
                         "`rtloop io list` shows what answers on the bus)")
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFFFFFFFF:
        raise JointError(f"{where}.{key}", f"expected an integer 0..0xFFFFFFFF, got {value!r}")
    return value


def _objects(table: dict[str, Any], key: str, where: str, default: tuple[int, ...], direction: str) -> tuple[int, ...]:
    value = table.get(key)
    if value is None:
        return default
    if not isinstance(value, list) or not value:
        raise JointError(f"{where}.{key}", "expected a list of object indices, e.g. ['0x6040', '0x607A']")
    objects = []
    for i, item in enumerate(value):
        try:
            index = parse_object(item)
        except ValueError as error:
            raise JointError(f"{where}.{key}[{i}]", str(error)) from None
        if OBJECTS[index].direction != direction:
            side = "RxPDO (master → drive)" if direction == "rx" else "TxPDO (drive → master)"
            raise JointError(f"{where}.{key}[{i}]", f"0x{index:04X} ({OBJECTS[index].name}) does not go in the {side}")
        if index in objects:
            raise JointError(f"{where}.{key}[{i}]", f"0x{index:04X} is mapped twice")
        objects.append(index)
    return tuple(objects)


DESCRIPTION_FILE_MAX_BYTES = 32 << 20
"""An ESI or EDS file larger than this is refused: a vendor's ESI for a whole family of drives is a
few MB; a 2 GB file (or /dev/zero behind a symlink) would be read into memory before the app starts."""


def read_description_file(path: Path, key: str, what: str) -> bytes:
    """The bytes of a drive's ESI or EDS file (``what``), refused (naming ``key``) when it is missing,
    not a regular file (a directory, a FIFO that blocks forever, a device) or too large."""
    try:
        status = path.stat()
    except FileNotFoundError:
        raise JointError(key, f"{path}: no such file") from None
    except OSError as error:
        raise JointError(key, f"{path}: cannot read it as {what} ({error.strerror or error})") from None
    if not stat.S_ISREG(status.st_mode):
        raise JointError(key, f"{path}: not a regular file, so not {what}")
    if status.st_size > DESCRIPTION_FILE_MAX_BYTES:
        raise JointError(key, f"{path}: {status.st_size} bytes, more than {what} rtloop reads "
                         f"({DESCRIPTION_FILE_MAX_BYTES >> 20} MiB)")
    try:
        with path.open("rb") as file:
            data = file.read(DESCRIPTION_FILE_MAX_BYTES + 1)  # a file growing meanwhile stops here
    except OSError as error:
        raise JointError(key, f"{path}: cannot read it as {what} ({error.strerror or error})") from None
    if len(data) > DESCRIPTION_FILE_MAX_BYTES:
        raise JointError(key, f"{path}: more than {what} rtloop reads ({DESCRIPTION_FILE_MAX_BYTES >> 20} MiB)")
    return data


def _refuse_entity(name: str, *_: Any) -> None:
    raise ValueError(f"it declares the entity {name!r}; an ESI file has no DTD entities (refused, not expanded)")


def _parse_esi_xml(data: bytes) -> ElementTree.Element:
    """The XML tree, after a first pass that refuses any entity declaration: nothing is expanded (a
    billion laughs) or fetched (an external entity), whatever the expat version's own limits."""
    checker = expat.ParserCreate()
    checker.EntityDeclHandler = _refuse_entity
    checker.Parse(data, True)
    return ElementTree.fromstring(data)


def read_esi(path: Path, where: str) -> tuple[Identity, tuple[int, ...], tuple[int, ...], bool]:
    """An ESI file's first device: identity, the objects of its first RxPDO and TxPDO, and whether
    it describes a distributed clocks operation mode (``Dc/OpMode`` with a non-zero AssignActivate)."""
    data = read_description_file(path, f"{where}.esi", "an ESI file")
    try:
        root = _parse_esi_xml(data)
    except (ValueError, expat.ExpatError, ElementTree.ParseError) as error:
        raise JointError(f"{where}.esi", f"{path}: cannot read it as an ESI file ({error})") from None

    def number(text: str | None) -> int:
        text = (text or "").strip()
        return int(text[2:], 16) if text.startswith("#x") else int(text or "0", 0)

    try:
        vendor = number(root.findtext("Vendor/Id"))
        device = root.find("Descriptions/Devices/Device")
        if device is None:
            raise ValueError("no Descriptions/Devices/Device")
        kind = device.find("Type")
        if kind is None:
            raise ValueError("no Device/Type")
        identity = Identity(vendor, number(kind.get("ProductCode")), number(kind.get("RevisionNo")))
        for field, value in (("vendor", identity.vendor), ("product code", identity.product),
                             ("revision", identity.revision)):
            if not 0 <= value <= 0xFFFFFFFF:  # what the SII holds: 32 bits each
                raise ValueError(f"its {field} {value} is not a 32-bit number")
        mappings = []
        for tag in ("RxPdo", "TxPdo"):
            pdo = device.find(tag)
            entries = [] if pdo is None else [number(e.findtext("Index")) for e in pdo.findall("Entry")]
            mappings.append(tuple(index for index in entries if index))
        has_dc = any(number(mode.findtext("AssignActivate")) for mode in device.findall("Dc/OpMode"))
    except ValueError as error:
        raise JointError(f"{where}.esi", f"{path}: not an ESI file rtloop reads ({error})") from None
    for index in (*mappings[0], *mappings[1]):
        if index not in OBJECTS:
            raise JointError(f"{where}.esi", f"{path}: maps object 0x{index:04X}, which rtloop does not map")
    return identity, mappings[0], mappings[1], has_dc


def _drive(table: dict[str, Any], where: str, counts_per_rev: float, rated: float, modes: tuple[int, ...]) -> \
        DriveParameters:
    given = table.get("drive", {})
    if not isinstance(given, dict):
        raise JointError(f"{where}.drive", "expected a table of the emulated drive's parameters")
    known = {f.name for f in dataclasses.fields(DriveParameters)} - {"counts_per_rev", "rated_torque_Nm", "modes"}
    for key, value in given.items():
        if key not in known:
            raise JointError(f"{where}.drive.{key}", f"unknown; expected one of {sorted(known)}")
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise JointError(f"{where}.drive.{key}", f"expected a number, got {value!r}")
    values: dict[str, Any] = {key: (int(value) if key == "following_error_window" else float(value))
                              for key, value in given.items()}
    parameters = DriveParameters(counts_per_rev=int(counts_per_rev), rated_torque_Nm=rated, modes=(8, 9, 10),
                                 **values)
    problem = parameters.problem()
    if problem:
        raise JointError(f"{where}.drive", problem)
    return parameters


def joint_from_table(table: Any, slave: int, base_dir: Path | None = None) -> JointConfig:
    where = f"joints[{slave - 1}]"
    if not isinstance(table, dict):
        raise JointError(where, "expected a table { name, vendor, product, revision, mode, counts_per_rev, ... }")
    unknown = sorted(set(table) - JOINT_KEYS)
    if unknown:
        raise JointError(f"{where}.{unknown[0]}", f"unknown key; expected some of {sorted(JOINT_KEYS)}")
    name = table.get("name")
    if not isinstance(name, str) or not name.isidentifier() or len(name) > 24:
        raise JointError(f"{where}.name", f"expected a name of letters, digits and underscores, got {name!r}")
    esi_identity, esi_dc = None, None
    default_rx: tuple[int, ...] = DEFAULT_RXPDO
    default_tx: tuple[int, ...] = DEFAULT_TXPDO
    if "esi" in table:
        path = Path(str(table["esi"]))
        if base_dir is not None and not path.is_absolute():
            path = base_dir / path
        esi_identity, default_rx, default_tx, esi_dc = read_esi(path, where)
    identity = Identity(_id(table, "vendor", where, esi_identity), _id(table, "product", where, esi_identity),
                        _id(table, "revision", where, esi_identity))
    if "mode" in table and "modes" in table:
        raise JointError(f"{where}.modes", "give mode (one) or modes (the first is the start), not both")
    mode_names = table.get("modes", [table.get("mode", "csp")])
    if not isinstance(mode_names, list) or not mode_names:
        raise JointError(f"{where}.modes", "expected a list such as ['csp', 'csv']")
    modes = []
    for text in mode_names:
        if not isinstance(text, str) or text not in MODES:
            raise JointError(f"{where}.mode{'s' if 'modes' in table else ''}",
                             f"{text!r} is not a mode rtloop drives; expected one of {sorted(MODES)} "
                             "(cyclic synchronous position, velocity, torque)")
        if MODES[text] in modes:
            raise JointError(f"{where}.modes", f"{text!r} is listed twice")
        modes.append(MODES[text])
    scale = JointScale(_number(table, "counts_per_rev", where), _number(table, "gear_ratio", where, 1.0),
                       int(_number(table, "direction", where, 1)), _number(table, "rated_torque_Nm", where, 1.0))
    problem = scale.problem()
    if problem:
        raise JointError(where, problem)
    rx = _objects(table, "rxpdo", where, default_rx, "rx")
    tx = _objects(table, "txpdo", where, default_tx, "tx")
    for index, side, key in ((cia402.CONTROLWORD, rx, "rxpdo"), (cia402.STATUSWORD, tx, "txpdo"),
                             (cia402.POSITION_ACTUAL, tx, "txpdo")):
        if index not in side:
            raise JointError(f"{where}.{key}", f"object 0x{index:04X} ({OBJECTS[index].name}) is missing from the "
                             "mapping: rtloop needs it to drive a CiA 402 drive")
    if cia402.MODES_OF_OPERATION not in rx:
        raise JointError(f"{where}.rxpdo", "object 0x6060 (modes of operation) is missing from the mapping: rtloop "
                         "selects the mode through it")
    for mode in modes:
        target = cia402.MODE_TARGETS[mode]
        if target not in rx:
            raise JointError(f"{where}.rxpdo", f"mode {cia402.MODE_NAMES[mode]} needs object 0x{target:04X} "
                             f"({OBJECTS[target].name}) in the mapping; it is missing")
    drive = _drive(table, where, scale.counts_per_rev, scale.rated_torque_Nm, tuple(modes))
    dc = table.get("dc")
    if dc is not None and not isinstance(dc, bool):
        raise JointError(f"{where}.dc", f"expected true (distributed clocks) or false (free run), got {dc!r}")
    if dc and esi_dc is False:
        raise JointError(f"{where}.dc", "the joint's ESI file describes no distributed clocks mode (Dc/OpMode): "
                         "the drive cannot run on them")
    return JointConfig(name, slave, identity, tuple(modes), scale, PdoLayout(rx), PdoLayout(tx), drive, dc, esi_dc)
