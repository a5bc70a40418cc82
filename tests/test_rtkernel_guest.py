"""The PREEMPT_RT test guest itself: its kernel is real-time, and every test device works.

These run only in the guest (``tools/rtkernel-vm.sh .venv/bin/python -m pytest -m rtkernel``,
docs/rtkernel-guest.md) and are skipped elsewhere, saying so. Each device is checked by what
its kernel driver does (a frame arrives, a register holds a value, a line reads back), through
the plain Linux interfaces, so a failure here is the guest's, not a device module's of rtloop.
Nothing about time is asserted: the guest is emulated.
"""

from __future__ import annotations

import ctypes
import fcntl
import json
import os
import select
import socket
import struct
import subprocess
import sys
import termios
import tty
from pathlib import Path

import pytest

from conftest import guest_device, scaled_ns, scaled_s, slowdown

pytestmark = pytest.mark.rtkernel


def test_the_kernel_is_preempt_rt(rtkernel_guest: dict) -> None:
    assert Path("/sys/kernel/realtime").read_text().strip() == "1"
    assert "PREEMPT_RT" in os.uname().version
    assert rtkernel_guest["kernel"] == os.uname().release


def test_sched_fifo_and_mlockall_are_granted(rtkernel_guest: dict) -> None:
    probe = (
        "import os; from rtloop.linux import rt\n"
        "os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80)); rt.lock_memory()\n"
        "locked = [line for line in open('/proc/self/status') if line.startswith('VmLck')][0].split()[1]\n"
        "print(os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, locked)\n"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=scaled_s(30))
    assert result.returncode == 0, result.stderr
    policy, priority, locked_kb = (int(word) for word in result.stdout.split())
    assert (policy, priority) == (os.SCHED_FIFO, 80)
    assert locked_kb > 1000, "mlockall should lock the whole process"


# --- CAN -----------------------------------------------------------------------------------------
CAN_FRAME = struct.Struct("=IB3x8s")  # struct can_frame: id, length, padding, data
CANFD_FRAME = struct.Struct("=IBBxx64s")  # struct canfd_frame: id, length, flags, padding, data


def _can_socket(interface: str, *, fd: bool = False) -> socket.socket:
    sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    if fd:
        sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FD_FRAMES, 1)
    sock.settimeout(30)
    sock.bind((interface,))
    return sock


def test_vcan_carries_can_fd_frames() -> None:
    interface = guest_device("vcan")["interface"]
    assert Path(f"/sys/class/net/{interface}/mtu").read_text().strip() == "72"
    with _can_socket(interface, fd=True) as receiver, _can_socket(interface, fd=True) as sender:
        payload = bytes(range(64))
        sender.send(CANFD_FRAME.pack(0x123, 64, 0, payload))
        can_id, length, _flags, data = CANFD_FRAME.unpack(receiver.recv(CANFD_FRAME.size))
    assert (can_id, length, data) == (0x123, 64, payload)


def test_a_frame_sent_on_one_emulated_can_controller_arrives_on_the_other() -> None:
    first, second = guest_device("can")["interfaces"]
    for interface in (first, second):
        assert Path(f"/sys/class/net/{interface}/flags").read_text().strip() != "0x0"
    with _can_socket(second) as receiver, _can_socket(first) as sender:
        sender.send(CAN_FRAME.pack(0x42, 3, b"abc".ljust(8, b"\0")))
        can_id, length, data = CAN_FRAME.unpack(receiver.recv(CAN_FRAME.size))
    assert (can_id, length, data[:length]) == (0x42, 3, b"abc")


# --- I2C: i2c-stub through i2c-dev, SMBus transfers -------------------------------------------------
I2C_SLAVE = 0x0703
I2C_SMBUS = 0x0720
SMBUS_READ, SMBUS_WRITE, SMBUS_BYTE_DATA = 1, 0, 2


class _SmbusIoctl(ctypes.Structure):
    _fields_ = (("read_write", ctypes.c_uint8), ("command", ctypes.c_uint8), ("size", ctypes.c_uint32),
                ("data", ctypes.POINTER(ctypes.c_uint8 * 34)))


def _smbus_byte(fd: int, read_write: int, register: int, value: int = 0) -> int:
    data = (ctypes.c_uint8 * 34)(value)
    request = _SmbusIoctl(read_write, register, SMBUS_BYTE_DATA, ctypes.pointer(data))
    fcntl.ioctl(fd, I2C_SMBUS, request)
    return data[0]


def test_i2c_stub_chips_keep_what_is_written_to_their_registers() -> None:
    i2c = guest_device("i2c")
    assert i2c["addresses"] == [0x48, 0x68]
    fd = os.open(i2c["device"], os.O_RDWR)
    try:
        for address, value in zip(i2c["addresses"], (0x5A, 0xC3), strict=True):
            fcntl.ioctl(fd, I2C_SLAVE, address)
            _smbus_byte(fd, SMBUS_WRITE, 0x10, value)
        for address, value in zip(i2c["addresses"], (0x5A, 0xC3), strict=True):
            fcntl.ioctl(fd, I2C_SLAVE, address)
            assert _smbus_byte(fd, SMBUS_READ, 0x10) == value
    finally:
        os.close(fd)


# --- uinput: a virtual button seen through evdev ------------------------------------------------
UI_SET_EVBIT, UI_SET_KEYBIT = 0x40045564, 0x40045565
UI_DEV_CREATE, UI_DEV_DESTROY = 0x5501, 0x5502
EV_SYN, EV_KEY, KEY_STOP = 0, 1, 128
INPUT_EVENT = struct.Struct("llHHi")


def test_a_uinput_button_press_arrives_on_its_event_device() -> None:
    uinput = guest_device("uinput")["device"]
    name = f"rtloop-test-estop-{os.getpid()}"
    fd = os.open(uinput, os.O_WRONLY | os.O_NONBLOCK)
    try:
        fcntl.ioctl(fd, UI_SET_EVBIT, EV_KEY)
        fcntl.ioctl(fd, UI_SET_KEYBIT, KEY_STOP)
        # struct uinput_user_dev: name[80], input_id (4 x u16), ff_effects_max, abs arrays (4 x 64 x s32)
        os.write(fd, name.encode().ljust(80, b"\0") + struct.pack("4HI", 3, 1, 1, 1, 0) + bytes(4 * 64 * 4))
        fcntl.ioctl(fd, UI_DEV_CREATE)
        events = [path for path in Path("/sys/class/input").glob("event*")
                  if (path / "device" / "name").read_text().strip() == name]
        assert len(events) == 1, f"no event device named {name}"
        reader = os.open(f"/dev/input/{events[0].name}", os.O_RDONLY)
        try:
            for kind, code, value in ((EV_KEY, KEY_STOP, 1), (EV_SYN, 0, 0)):
                os.write(fd, INPUT_EVENT.pack(0, 0, kind, code, value))
            assert select.select([reader], [], [], 30)[0], "the key press did not arrive"
            _sec, _usec, kind, code, value = INPUT_EVENT.unpack(os.read(reader, INPUT_EVENT.size))
            assert (kind, code, value) == (EV_KEY, KEY_STOP, 1)
        finally:
            os.close(reader)
        fcntl.ioctl(fd, UI_DEV_DESTROY)
    finally:
        os.close(fd)


# --- GPIO: gpio-sim through the GPIO character device (uAPI v2) -----------------------------------
GPIO_GET_CHIPINFO = 0x8044B401  # struct gpiochip_info: name[32], label[32], lines
GPIO_V2_GET_LINEINFO = 0xC100B405  # struct gpio_v2_line_info, 256 bytes
GPIO_V2_GET_LINE = 0xC250B407  # struct gpio_v2_line_request, 592 bytes
GPIO_V2_LINE_GET_VALUES, GPIO_V2_LINE_SET_VALUES = 0xC010B40E, 0xC010B40F
GPIO_V2_LINE_FLAG_INPUT, GPIO_V2_LINE_FLAG_OUTPUT = 1 << 2, 1 << 3


def _request_line(chip_fd: int, offset: int, flags: int) -> int:
    request = bytearray(592)
    struct.pack_into("I", request, 0, offset)  # offsets[64]
    request[256:256 + 11] = b"rtloop-test"  # consumer[32]
    struct.pack_into("Q", request, 288, flags)  # config.flags
    struct.pack_into("I", request, 560, 1)  # num_lines
    fcntl.ioctl(chip_fd, GPIO_V2_GET_LINE, request)
    return struct.unpack_from("i", request, 588)[0]  # fd


def test_gpio_sim_lines_have_their_names_and_move_both_ways() -> None:
    gpio = guest_device("gpio")
    lines, sim = gpio["lines"], Path(gpio["sim"])
    chip = os.open(gpio["device"], os.O_RDWR)
    try:
        info = bytearray(68)
        fcntl.ioctl(chip, GPIO_GET_CHIPINFO, info)
        assert info[32:64].rstrip(b"\0") == b"rtloop-sim" and struct.unpack_from("I", info, 64)[0] == len(lines)
        for name, line in lines.items():
            line_info = bytearray(256)
            struct.pack_into("I", line_info, 64, line["offset"])
            fcntl.ioctl(chip, GPIO_V2_GET_LINEINFO, line_info)
            assert line_info[:32].rstrip(b"\0").decode() == name
        # an input follows what the simulator pulls it to
        button = _request_line(chip, lines["button"]["offset"], GPIO_V2_LINE_FLAG_INPUT)
        try:
            for pull, expected in (("pull-up", 1), ("pull-down", 0)):
                (sim / f"sim_gpio{lines['button']['offset']}" / "pull").write_text(pull)
                values = bytearray(struct.pack("QQ", 0, 1))
                fcntl.ioctl(button, GPIO_V2_LINE_GET_VALUES, values)
                assert struct.unpack("QQ", values)[0] & 1 == expected
        finally:
            os.close(button)
        # an output shows on the simulator's side
        led = _request_line(chip, lines["led"]["offset"], GPIO_V2_LINE_FLAG_OUTPUT)
        try:
            for value in (1, 0):
                fcntl.ioctl(led, GPIO_V2_LINE_SET_VALUES, bytearray(struct.pack("QQ", value, 1)))
                assert (sim / f"sim_gpio{lines['led']['offset']}" / "value").read_text().strip() == str(value)
        finally:
            os.close(led)
    finally:
        os.close(chip)


# --- SPI: our loopback controller through spidev ------------------------------------------------
SPI_IOC_MESSAGE_1 = 0x40206B00  # _IOW('k', 0, struct spi_ioc_transfer)


def test_spidev_on_the_loopback_controller_receives_what_it_sends() -> None:
    spi = guest_device("spi")
    assert len(spi["devices"]) == 2
    sent = bytes(range(1, 33))
    for device in spi["devices"]:
        tx = ctypes.create_string_buffer(sent, len(sent))
        rx = ctypes.create_string_buffer(len(sent))
        # struct spi_ioc_transfer: tx_buf, rx_buf, len, speed_hz, delay_usecs, bits_per_word, cs_change,
        # tx_nbits, rx_nbits, word_delay_usecs, padding
        transfer = bytearray(struct.pack("QQIIHBBBBBx", ctypes.addressof(tx), ctypes.addressof(rx), len(sent),
                                         1_000_000, 0, 8, 0, 0, 0, 0))
        fd = os.open(device, os.O_RDWR)
        try:
            assert fcntl.ioctl(fd, SPI_IOC_MESSAGE_1, transfer) == len(sent)
        finally:
            os.close(fd)
        assert rx.raw == sent, device


# --- serial: a UART wired to an emulated USB serial adapter; ptys ---------------------------------
def _read_exactly(fd: int, count: int) -> bytes:
    got = b""
    while len(got) < count:
        assert select.select([fd], [], [], 30)[0], f"only {got!r} arrived"
        got += os.read(fd, count - len(got))
    return got


def test_bytes_cross_the_uart_to_usb_serial_loop_both_ways() -> None:
    uart_path, usb_path = guest_device("serial")["pair"]
    uart = os.open(uart_path, os.O_RDWR | os.O_NOCTTY)
    usb = os.open(usb_path, os.O_RDWR | os.O_NOCTTY)
    try:
        for fd in (uart, usb):
            tty.setraw(fd)
            termios.tcflush(fd, termios.TCIOFLUSH)
        for writer, reader, message in ((uart, usb, b"ping\x00\xff"), (usb, uart, b"pong\r\n")):
            os.write(writer, message)
            assert _read_exactly(reader, len(message)) == message
    finally:
        os.close(uart)
        os.close(usb)


def test_a_pty_pair_carries_bytes(rtkernel_guest: dict) -> None:
    controller, terminal = os.openpty()
    try:
        tty.setraw(terminal)
        os.write(controller, b"rtloop")
        assert _read_exactly(terminal, 6) == b"rtloop"
    finally:
        os.close(controller)
        os.close(terminal)


# --- the JIWY demo on the RT kernel ---------------------------------------------------------------
JIWY = Path(__file__).resolve().parents[1] / "examples" / "jiwy"


def _first_unclean_release_ns(timing_csv: Path, period_ns: int) -> int:
    """Release time (since the first release) of the first cycle that ended late or was skipped."""
    rows = [line.split(",") for line in timing_csv.read_text().splitlines()[1:]]
    summary = json.loads((timing_csv.parent / "summary.json").read_text())
    counts = {name: (task["cycles"], task["overruns"]) for name, task in summary["tasks"].items()}
    assert rows, f"no cycle ran (cycles, overruns): {counts}"
    first_release = min(int(row[2]) for row in rows)
    worst, last_cycle = 10**18, {}
    for task, cycle, release, _start, end in rows:
        skipped = task in last_cycle and int(cycle) != last_cycle[task] + 1
        last_cycle[task] = int(cycle)
        if skipped or int(end) > int(release) + period_ns:
            worst = min(worst, int(release) - first_release)
    return worst


@pytest.mark.rt
@pytest.mark.timeout(scaled_s(300))  # a simulation, up to three runs and a report, each a few processes
def test_jiwy_runs_on_the_rt_kernel_writes_its_report_and_reproduces_its_simulation(
    tmp_path: Path, rtloop_env: dict[str, str], rtkernel_guest: dict
) -> None:
    # The demo as it is, at a rate the machine keeps up with: run == simulate is a property of the
    # schedule, whatever the period. 1 kHz on hardware (1,000 cycles, the step at 0.5 s). Under
    # emulation JIWY's step takes a few ms, but a busy host stalls the whole guest for tens of ms
    # at a time, which ends a 20 ms cycle late: 10 Hz there (200 cycles, the step at cycle 5).
    emulated = slowdown() > 1
    period_ns = scaled_ns(5_000_000 if emulated else 1_000_000)
    text = (JIWY / "jiwy.toml").read_text()
    assert text.count("period_ns = 1_000_000") == 2
    app = tmp_path / "jiwy.toml"
    app.write_text(text.replace("period_ns = 1_000_000", f"period_ns = {period_ns}"))
    duration_s = str((200 if emulated else 1000) * period_ns / 1e9)
    feed = f"setpoint={JIWY / 'setpoints' / 'step.csv'}"
    rtloop = [sys.executable, "-m", "rtloop.cli"]
    timeout_s = scaled_s(60)

    def cli(*arguments: str) -> None:
        result = subprocess.run([*rtloop, *arguments], env=rtloop_env, capture_output=True, text=True,
                                timeout=timeout_s)
        assert result.returncode == 0, f"rtloop {' '.join(arguments)}: {result.stderr}"

    cli("simulate", str(app), "--duration", duration_s, "--feed", feed, "--out", str(tmp_path / "sim"), "-q")
    simulated = (tmp_path / "sim" / "signals.csv").read_text().splitlines()
    compared_rows, misses = 0, []
    for attempt in range(3):  # a host that stalls the whole guest can spoil a run; the rule stays the same
        out = tmp_path / f"run{attempt}"
        cli("run", str(app), "--duration", duration_s, "--feed", feed, "--out", str(out), "-q")
        horizon_ns = _first_unclean_release_ns(out / "timing.csv", period_ns)
        tasks = json.loads((out / "summary.json").read_text())["tasks"]
        misses.append((horizon_ns / 1e9, {name: (task["cycles"], task["overruns"], task["stale_connection_reads"])
                                          for name, task in tasks.items()}))
        ran = (out / "signals.csv").read_text().splitlines()
        assert ran[0] == simulated[0]
        compared_rows = 0
        for sim_row, run_row in zip(simulated[1:], ran[1:], strict=False):
            if round(float(sim_row.split(",")[0]) * 1e9) >= horizon_ns:
                break
            assert run_row == sim_row, f"run and simulation differ at t = {sim_row.split(',')[0]} s"
            compared_rows += 1
        if compared_rows >= 100:
            break
    assert compared_rows >= 100, ("no run stayed on schedule for 100 cycles: (first late or skipped release in s, "
                                  f"{{task: (cycles, overruns, stale reads)}}) of each run: {misses}")
    cli("report", str(out))
    assert (out / "report.html").stat().st_size > 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["rt_capable"] is True
    assert {task["policy"] for task in summary["tasks"].values()} == {"fifo"}
