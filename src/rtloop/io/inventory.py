"""What this machine offers devices: GPIO chips, CAN interfaces, spidev, serial lines, I2C buses.

``rtloop io list`` prints it; ``rtloop doctor`` sums it up. For each interface: what it is
(a chip's label and line count, a CAN interface's state and bit rate, a UART's driver, an
I2C adapter's name) and whether this user may open it, with the fix when not. Everything is
read from ``/dev`` and ``/sys`` under ``root`` (``/`` on a live system; the tests point it at
a prepared tree), plus ``gpiod`` for line names and ``ip -details`` for CAN states when they
are there.
"""

from __future__ import annotations

import grp
import json
import os
import re
import shutil
import stat
import subprocess
from dataclasses import asdict, dataclass
from pathlib import Path

KIND_ORDER = ("gpio", "can", "spi", "serial", "i2c")
ARPHRD_CAN = "280"


@dataclass(frozen=True, slots=True)
class Interface:
    """One interface a device could use."""

    kind: str
    """``gpio``, ``can``, ``spi``, ``serial`` or ``i2c`` (the ``kind`` of ``[devices.NAME]``)."""
    path: str
    """What the app file names: ``/dev/gpiochip0``, ``can0``, ``/dev/spidev0.0``, ``/dev/ttyUSB0``, ``/dev/i2c-1``."""
    detail: str
    """What it is: label and lines, state and bit rate, driver, adapter name."""
    usable: bool
    """Whether this user may open it now."""
    fix: str = ""
    """What to do when it is not usable."""

    def to_json(self) -> dict[str, object]:
        return asdict(self)


def _read(path: Path) -> str:
    try:
        return path.read_text().strip()
    except OSError:
        return ""


def _access(node: Path) -> tuple[bool, str]:
    """May this user read and write the device node? If not, the fix."""
    if os.access(node, os.R_OK | os.W_OK):
        return True, ""
    try:
        status = node.stat()
    except OSError as error:
        return False, f"cannot look at it: {error.strerror}"
    try:
        group = grp.getgrgid(status.st_gid).gr_name
    except KeyError:
        group = str(status.st_gid)
    mode = stat.filemode(status.st_mode)
    if group == "root":
        return False, (f"{mode} root:root; add a udev rule giving it a group you are in, e.g. "
                       f'SUBSYSTEM=="{node.name.rstrip("0123456789.-")}", GROUP="plugdev", MODE="0660"')
    return False, f"{mode}, group {group}: sudo usermod -aG {group} $USER, then log in again"


def _nodes(root: Path, pattern: str) -> list[Path]:
    dev = root / "dev"
    found = [path for path in dev.glob(pattern) if path.exists()]
    return sorted(found, key=lambda p: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)])


def gpio_chips(root: Path) -> list[Interface]:
    chips = []
    for node in _nodes(root, "gpiochip*"):
        usable, fix = _access(node)
        detail = _read(root / "sys" / "bus" / "gpio" / "devices" / node.name / "label")
        try:
            if root != Path("/"):
                raise ImportError("a prepared tree")
            import gpiod

            with gpiod.Chip(str(node)) as chip:
                info = chip.get_info()
                named = [chip.get_line_info(i).name for i in range(info.num_lines)]
                used = sum(chip.get_line_info(i).used for i in range(info.num_lines))
            names = ", ".join(n for n in named[:8] if n) + (" …" if len(named) > 8 else "")
            detail = f"{info.label}: {info.num_lines} lines, {used} in use" + (f" ({names})" if names else "")
        except ImportError:
            detail = (detail + ": " if detail else "") + "lines not listed (pip install 'rtloop[gpio]' to see them)"
        except OSError as error:
            detail = f"cannot read its lines: {error.strerror}"
        chips.append(Interface("gpio", f"/dev/{node.name}", detail, usable, fix))
    return chips


def _can_details(name: str) -> dict[str, object]:
    if shutil.which("ip") is None:
        return {}
    try:
        text = subprocess.run(["ip", "-details", "-json", "link", "show", "dev", name], capture_output=True,
                              text=True, timeout=5, check=True).stdout
        linkinfo: dict[str, object] = json.loads(text)[0].get("linkinfo", {})
        return linkinfo
    except (OSError, subprocess.SubprocessError, ValueError, IndexError):
        return {}


def can_interfaces(root: Path) -> list[Interface]:
    interfaces = []
    net = root / "sys" / "class" / "net"
    for entry in sorted(net.iterdir()) if net.is_dir() else []:
        if _read(entry / "type") != ARPHRD_CAN:
            continue
        name = entry.name
        operstate = _read(entry / "operstate") or "unknown"
        flags = int(_read(entry / "flags") or "0", 16)
        up = bool(flags & 0x1)  # IFF_UP
        info = _can_details(name) if root == Path("/") else {}
        kind = str(info.get("info_kind", "can"))
        data = info.get("info_data", {}) if isinstance(info.get("info_data"), dict) else {}
        parts = [kind, "up" if up else "down", operstate]
        if isinstance(data, dict) and data.get("state"):
            parts.append(str(data["state"]))
        bittiming = data.get("bittiming", {}) if isinstance(data, dict) else {}
        if isinstance(bittiming, dict) and bittiming.get("bitrate"):
            parts.append(f"{bittiming['bitrate']} bit/s")
        mtu = _read(entry / "mtu")
        parts.append("CAN FD" if mtu == "72" else "classic CAN")
        fix = ""
        if not up:
            fix = (f"sudo ip link set {name} up" if kind == "vcan" or name.startswith("vcan")
                   else f"sudo ip link set {name} up type can bitrate 500000 (your bus's bit rate)")
        interfaces.append(Interface("can", name, ", ".join(parts), up, fix))
    return interfaces


def spi_devices(root: Path) -> list[Interface]:
    return [Interface("spi", f"/dev/{node.name}", "spidev", *_access(node)) for node in _nodes(root, "spidev*")]


def serial_lines(root: Path) -> list[Interface]:
    lines = []
    tty = root / "sys" / "class" / "tty"
    for entry in sorted(tty.iterdir()) if tty.is_dir() else []:
        name = entry.name
        if not re.fullmatch(r"tty(S|USB|ACM|AMA|AML|MFD|SC|XRUSB)\d+", name):
            continue
        driver = entry / "device" / "driver"
        if not driver.exists():
            continue
        if name.startswith("ttyS") and _read(entry / "type") in ("", "0"):  # a legacy port with no UART behind it
            continue
        node = root / "dev" / name
        if not node.exists():
            continue
        detail = f"driver {_driver_of(entry / 'device')}"
        if name.startswith("ttyUSB"):
            latency = _read(entry / "device" / "latency_timer")
            if latency:
                detail += f", latency_timer {latency} ms" + (" (set 1 for a 1 kHz loop)" if latency != "1" else "")
        lines.append(Interface("serial", f"/dev/{name}", detail, *_access(node)))
    return lines


def _driver_of(device: Path) -> str:
    """The driver of a tty's hardware (newer kernels put a serial-base ``port`` device in between)."""
    here = Path(os.path.realpath(device))
    while len(here.parts) > 3:
        driver = here / "driver"
        if driver.exists():
            name = os.path.basename(os.path.realpath(driver))
            if name not in ("port", "ctrl"):
                return name
        here = here.parent
    return "unknown"


def i2c_buses(root: Path) -> list[Interface]:
    buses = []
    for node in _nodes(root, "i2c-*"):
        name = _read(root / "sys" / "class" / "i2c-dev" / node.name / "name")
        buses.append(Interface("i2c", f"/dev/{node.name}", name or "I2C adapter", *_access(node)))
    return buses


def list_interfaces(root: Path = Path("/")) -> list[Interface]:
    """Every interface on the machine under ``root``, in the order of :data:`KIND_ORDER`."""
    return [*gpio_chips(root), *can_interfaces(root), *spi_devices(root), *serial_lines(root), *i2c_buses(root)]


def format_table(interfaces: list[Interface]) -> str:
    if not interfaces:
        return ("no GPIO chip, CAN interface, spidev, serial line or I2C bus on this machine "
                "(this kernel may lack them: see docs/devices.md for the test kernel's guest)")
    kind = max(7, *(len(item.kind) + 1 for item in interfaces))  # 'ethercat', 'canopen' and a space
    lines = [f"{'kind':<{kind}}{'interface':<22}{'may open':<10}detail"]
    for item in interfaces:
        lines.append(f"{item.kind:<{kind}}{item.path:<22}{'yes' if item.usable else 'NO':<10}{item.detail}")
        if item.fix:
            lines.append(f"{'':<{kind + 22}}fix: {item.fix}")
    missing = [kind for kind in KIND_ORDER if not any(i.kind == kind for i in interfaces)]
    if missing:
        lines.append(f"none of: {', '.join(missing)}")
    return "\n".join(lines)
