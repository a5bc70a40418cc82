"""Each driver's read + write per cycle next to the bare system call doing the same transfer, in one run.

For every device kind that this kernel offers, two loops run interleaved in batches, each cycle
timed around the device's part only:

- ``driver``  ``device.write(u)`` then ``device.read(y)``, as the task's loop calls them
              (values packed and unpacked through the declared layout, checks included);
- ``bare``    the same transfer with the same system calls on bytes prepared beforehand
              (no layout, no check): the floor any driver pays;
- ``reference`` (GPIO, SPI and CAN, where ``io/_devio.c`` was built) the same device with its C
              cycle set aside for the batch: the Python reference, in the same interleaving (CAN's
              keeps its layouts and drain in C: the path before its whole cycle went to C).

Where it runs:

- anywhere: CAN's per-cycle work over a UNIX datagram socket pair (the same send, poll and
  recv_into calls as on a CAN socket; the kernel's CAN stack itself is not in the figure);
- in the PREEMPT_RT test guest (``tools/rtkernel-vm.sh``): GPIO (gpio-sim), CAN (vcan0), SPI
  (loopback spidev), I2C (i2c-stub). The guest is emulated (TCG, 15-18x slower than the
  host, unevenly): its microseconds mean nothing; only the ratio in one run is compared.

Each contender's figure is its fastest batch (what the code costs when nothing else takes the
CPU, as ``timeit`` reports it); the medians are printed beside. The target is driver ≤ 1.3 ×
bare + 1 µs (host figures). Usage::

    python benchmarks/bench_devices.py                   # what this machine has
    tools/rtkernel-vm.sh .venv/bin/python benchmarks/bench_devices.py --cycles 2000
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import platform
import select
import socket
import struct
import sys
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np

from rtloop.io.compiled import devio
from rtloop.io.device import build_device

Pair = tuple[Callable[[], None], Callable[[], None]]  # (setup-free per-cycle peer work, cleanup)


def timed(work: Callable[[], None], peer: Callable[[], None], cycles: int) -> int:
    """Nanoseconds spent in ``work`` over ``cycles`` cycles (``peer`` runs between, untimed)."""
    clock = time.perf_counter_ns
    total = 0
    for _ in range(cycles):
        start = clock()
        work()
        total += clock() - start
        peer()
    return total


def compare(driver: Callable[[], None], bare: Callable[[], None], peer: Callable[[], None],
            cycles: int, rounds: int, reference: Callable[[bool], None] | None = None) -> dict[str, float]:
    """``reference(True)`` switches the driver to its Python reference, ``reference(False)`` back:
    then its batches run interleaved with the others too (``reference_*`` in the result)."""
    for _ in range(200):  # warm-up: caches, free lists, branch predictors
        driver(); peer(); bare(); peer()  # noqa: E702
    driver_ns, bare_ns, reference_ns = [], [], []
    for _ in range(rounds):
        driver_ns.append(timed(driver, peer, cycles) / cycles)
        bare_ns.append(timed(bare, peer, cycles) / cycles)
        if reference is not None:
            reference(True)
            try:
                reference_ns.append(timed(driver, peer, cycles) / cycles)
            finally:
                reference(False)
    # the fastest batch of each: what the code costs when nothing else takes the CPU (as timeit
    # reports), then the medians, which a busy machine moves
    d, b = min(driver_ns), min(bare_ns)
    result = {"driver_us": d / 1000, "bare_us": b / 1000, "ratio": d / b, "target_us": (1.3 * b + 1000) / 1000,
              "within_target": d <= 1.3 * b + 1000, "driver_median_us": float(np.median(driver_ns)) / 1000,
              "bare_median_us": float(np.median(bare_ns)) / 1000}
    if reference_ns:
        r = min(reference_ns)
        result.update({"reference_us": r / 1000, "reference_ratio": r / b, "reference_within_target":
                       r <= 1.3 * b + 1000, "reference_median_us": float(np.median(reference_ns)) / 1000})
    return result


def pty_line() -> tuple[int, int, str]:
    """A pseudo-terminal in a serial line's place: (master, slave, the slave's path for the device).
    The master is the far end (a drive, a bus of servos): blocking, as firmware waits for a request."""
    master, slave = os.openpty()
    os.set_blocking(master, True)
    return master, slave, os.ttyname(slave)


def bytes_kept(cycle: Callable[[], None], warmup: int, cycles: int) -> tuple[int, int]:
    """Bytes that ``cycles`` calls of ``cycle`` leave allocated (tracemalloc, after ``warmup`` calls
    under it: the interpreter's one-time caches come first): (by rtloop/io's files, by the whole
    process). Each line of rtloop/io that kept any is printed on stderr."""
    tracemalloc.start()
    for _ in range(warmup):
        cycle()
    before = tracemalloc.take_snapshot()
    for _ in range(cycles):
        cycle()
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    io_files = [tracemalloc.Filter(True, "*rtloop/io/*")]
    kept = after.filter_traces(io_files).compare_to(before.filter_traces(io_files), "lineno")
    for stat in kept:
        if stat.size_diff:
            print("kept:", stat, file=sys.stderr)
    return sum(s.size_diff for s in kept), sum(s.size_diff for s in after.compare_to(before, "lineno"))


def set_aside(device: object, attribute: str) -> Callable[[bool], None] | None:
    """Switch ``device`` between its C cycle (held in ``attribute``) and its Python reference (the
    attribute None); None when the C cycle is not there (not built, or RTLOOP_PURE_PYTHON=1)."""
    compiled = getattr(device, attribute)
    if compiled is None:
        return None
    return lambda python: setattr(device, attribute, None if python else compiled)


# --- CAN -------------------------------------------------------------------------------------------
CAN_SETTINGS = {
    "send": [{"id": 0x200, "signals": [{"name": "torque", "start_byte": 0, "type": "i16", "scale": 0.01},
                                       {"name": "mode", "start_byte": 2, "type": "u8"}]}],
    "receive": [{"id": 0x180, "timeout_ms": 100, "signals": [
        {"name": "position", "start_byte": 0, "type": "i32", "scale": 1e-4},
        {"name": "speed", "start_byte": 4, "type": "i16", "scale": 0.01}]}],
}
CAN_FRAME = struct.Struct("=IB3x8s")


def bench_can(ours: socket.socket, peer: socket.socket, device, cycles: int, rounds: int) -> dict[str, float]:
    from rtloop.io.cansocket import CanSocket

    device.attach(CanSocket("bench", False, device.received, "bench", sock=ours))
    answer = bytearray(CAN_FRAME.pack(0x180, 8, struct.pack("<ih2x", 12345, -250)))
    command = bytearray(CAN_FRAME.pack(0x200, 8, struct.pack("<hB5x", 50, 1)))
    incoming, mine = bytearray(72), bytearray(72)
    u, y = np.array([0.5, 1.0]), np.zeros(2)
    poller = select.poll()
    poller.register(ours.fileno(), select.POLLIN)

    def driver() -> None:
        device.write(u)
        device.read(y)

    def bare() -> None:  # the same calls: one send, drain with poll + recv_into
        ours.send(command)
        while poller.poll(0):
            ours.recv_into(mine)

    def answer_it() -> None:  # the drive: take the command, answer
        peer.recv_into(incoming)
        peer.send(answer)

    # the driver's read waits for an answer that came after its write: answer first, untimed
    peer.send(answer)
    result = compare(driver, bare, answer_it, cycles, rounds, set_aside(device, "_cycle"))
    assert abs(y[0] - 1.2345) < 1e-12 and y[1] == -2.5, y  # the answers were decoded
    return result


def can_on_socket_pair(cycles: int, rounds: int) -> dict[str, float]:
    device = build_device("can", "bench", {"interface": "pair", **CAN_SETTINGS}, "bench")
    ours, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        return bench_can(ours, peer, device, cycles, rounds)
    finally:
        ours.close()
        peer.close()


def can_on_vcan(interface: str, cycles: int, rounds: int) -> dict[str, float]:
    device = build_device("can", "bench", {"interface": interface, **CAN_SETTINGS}, "bench")
    from rtloop.io.cansocket import CanSocket

    ours = CanSocket(interface, False, device.received, "bench").sock
    peer = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    peer.bind((interface,))
    try:
        return bench_can(ours, peer, device, cycles, rounds)
    finally:
        ours.close()
        peer.close()


# --- GPIO, SPI, I2C (guest) ------------------------------------------------------------------------
def gpio(entry: dict, cycles: int, rounds: int) -> dict[str, float]:
    from rtloop.io.kernel import GPIO_V2_LINE_GET_VALUES_IOCTL, GPIO_V2_LINE_SET_VALUES_IOCTL, GPIO_V2_LINE_VALUES

    device = build_device("gpio", "bench", {"chip": entry["device"], "outputs": ["led", "enable"],
                                            "inputs": ["button", "fault"]}, "bench")
    device.configure()
    u, y = np.array([1.0, 0.0]), np.zeros(2)
    out_fd, in_fd = device._out_fd, device._in_fd
    set_values = bytearray(GPIO_V2_LINE_VALUES.pack(0b01, 0b11))
    get_values = bytearray(GPIO_V2_LINE_VALUES.pack(0, 0b11))

    def driver() -> None:
        device.write(u)
        device.read(y)

    def bare() -> None:
        fcntl.ioctl(out_fd, GPIO_V2_LINE_SET_VALUES_IOCTL, set_values, True)
        fcntl.ioctl(in_fd, GPIO_V2_LINE_GET_VALUES_IOCTL, get_values, True)

    try:
        return compare(driver, bare, lambda: None, cycles, rounds, set_aside(device, "_lines"))
    finally:
        device.close()


def spi(entry: dict, cycles: int, rounds: int) -> dict[str, float]:
    from rtloop.io.kernel import SPI_IOC_MESSAGE_1

    signals = [{"name": "pwm_pan", "start_byte": 1, "type": "i16", "scale": 0.001},
               {"name": "pwm_tilt", "start_byte": 3, "type": "i16", "scale": 0.001}]
    device = build_device("spi", "bench", {"device": entry["devices"][0], "length": 8, "send": signals,
                                           "receive": signals, "counter": "echo"}, "bench")
    device.configure()
    u, y = np.array([0.25, -0.5]), np.zeros(2)
    transfer = device._transfer  # the same prebuilt struct spi_ioc_transfer and buffers

    def driver() -> None:
        device.write(u)
        device.read(y)

    def bare() -> None:
        fcntl.ioctl(device.fd, SPI_IOC_MESSAGE_1, transfer, True)

    try:
        result = compare(driver, bare, lambda: None, cycles, rounds, set_aside(device, "_frame"))
        assert device.transfers_rejected == 0 and list(y) == [0.25, -0.5], (device.transfers_rejected, y)
        return result
    finally:
        device.close()


def i2c(entry: dict, cycles: int, rounds: int) -> dict[str, float]:
    from smbus2 import SMBus

    registers = [{"name": "duty", "register": 0x10, "type": "u8"}, {"name": "speed", "register": 0x20, "type": "i16"}]
    device = build_device("i2c", "bench", {"bus": entry["bus"], "address": entry["addresses"][0],
                                           "writes": registers, "reads": registers}, "bench")
    device.configure()
    u, y = np.array([7.0, -300.0]), np.zeros(2)
    bus = SMBus(entry["bus"])
    address = entry["addresses"][0]

    def driver() -> None:
        device.write(u)
        device.read(y)

    def bare() -> None:  # smbus2's own calls for the same four transfers
        bus.write_byte_data(address, 0x10, 7)
        bus.write_word_data(address, 0x20, 0xFED4)
        bus.read_byte_data(address, 0x10)
        bus.read_word_data(address, 0x20)

    try:
        return compare(driver, bare, lambda: None, cycles, rounds)
    finally:
        device.close()
        bus.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=1_000, help="cycles per batch")
    parser.add_argument("--rounds", type=int, default=30, help="batches of each contender, interleaved")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    in_guest = bool(os.environ.get("RTLOOP_GUEST_DEVICES"))
    results: dict[str, dict[str, float]] = {}
    results["can (UNIX socket pair)"] = can_on_socket_pair(args.cycles, args.rounds)
    if in_guest:
        devices = json.loads(Path(os.environ["RTLOOP_GUEST_DEVICES"]).read_text())["devices"]
        for kind, label, run in (("gpio", "gpio-sim", gpio), ("spi", "loopback spidev", spi),
                                 ("i2c", "i2c-stub", i2c)):
            if devices.get(kind, {}).get("present"):
                results[f"{kind} ({label})"] = run(devices[kind], args.cycles, args.rounds)
        if devices.get("vcan", {}).get("present"):
            results["can (vcan0)"] = can_on_vcan(devices["vcan"]["interface"], args.cycles, args.rounds)
    where = ("PREEMPT_RT test guest under TCG emulation: µs mean nothing, compare the ratio" if in_guest
             else f"{platform.node()}: {platform.release()}")
    path = "C (io/_devio.c)" if devio() is not None else "Python reference (RTLOOP_PURE_PYTHON=1 or not built)"
    load = os.getloadavg()[0]
    print(f"# bench_devices: {where}; drivers' per-cycle work: {path}; {args.rounds} batches x {args.cycles} "
          f"cycles each, interleaved; 1-min load average {load:.1f}\n")
    print("| device | path | driver write+read µs | bare calls µs | ratio | 1.3 x bare + 1 µs | within | medians µs |")
    print("|---|---|---:|---:|---:|---:|---|---|")
    for name, r in results.items():
        # I2C's driver has no C part: its row is Python either way
        driver_path = "C" if devio() is not None and not name.startswith("i2c") else "Python"
        print(f"| {name} | {driver_path} | {r['driver_us']:.2f} | {r['bare_us']:.2f} | {r['ratio']:.2f} | "
              f"{r['target_us']:.2f} | {'yes' if r['within_target'] else 'no'} | "
              f"{r['driver_median_us']:.2f} / {r['bare_median_us']:.2f} |")
        if "reference_us" in r:  # the same device, its C cycle set aside, in the same batches
            reference = "Python (layouts, drain in C)" if name.startswith("can") else "Python"
            print(f"| {name} | {reference} | {r['reference_us']:.2f} | {r['bare_us']:.2f} | "
                  f"{r['reference_ratio']:.2f} | {r['target_us']:.2f} | "
                  f"{'yes' if r['reference_within_target'] else 'no'} | "
                  f"{r['reference_median_us']:.2f} / {r['bare_median_us']:.2f} |")
    if args.json:
        args.json.write_text(json.dumps({"where": where, "path": path, "python": sys.version.split()[0],
                                         "load_average_1min": load, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
