"""The serial device's exchange per cycle next to the bare calls doing the same transfer, in one run;
and what the device loop allocates (tracemalloc over 10,000 cycles).

A pseudo-terminal stands in for the line; a responder on its master side answers each request
*between* timed cycles (untimed, as the drive would while the task sleeps), so the response is
waiting when the device looks for it and the figures are the host's share only. Contenders,
interleaved in batches (medians):

- ``device``    ``SerialDevice.write(u)`` + ``read(y)``: frame filled, sequence, CRC-16 out and
                back, length/sequence/CRC checked, readings copied;
- ``os calls``  the same transfer with the same system calls on bytes prepared beforehand: one
                ``os.write``, then ``poll`` + ``os.readv`` into a buffer (no frame, no check);
- ``pyserial``  pyserial's own ``write`` + ``read`` of the same bytes;
- ``framework`` ``TaskDevices.at_release`` with that device: the guard (finite, clamp, rate
                limit), the copies from and to the task's vectors, then the exchange.

Usage::

    python benchmarks/bench_serial.py                 # 5 x 10,000 cycles each
    python benchmarks/bench_serial.py --cycles 500 --rounds 2 --json out.json
"""

from __future__ import annotations

import argparse
import os
import select
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_output_options, where_measured, write_json
from bench_devices import bytes_kept, compare, pty_line

from rtloop.io.device import CommandLimit, build_device
from rtloop.io.host import DeviceWiring, TaskDevices
from rtloop.io.serial import ENABLED, REQUEST_SYNC, RESPONSE_SYNC, Frame

COMMANDS, READINGS = ["voltage_V", "brake"], ["speed_rad_s", "current_A", "temperature_C"]


class Responder:
    """The drive on the pty's master side: take a request, put the answer to the next one in place."""

    def __init__(self, master: int, device) -> None:
        self.master, self.device = master, device
        self.request = bytearray(Frame(REQUEST_SYNC, len(COMMANDS)).buffer)
        self.response = Frame(RESPONSE_SYNC, len(READINGS))
        self.response.values[:] = [123.25, 1.5, 40.0]

    def prepare(self) -> None:
        self.response.seal((self.device.sequence + 1) & 0xFF, ENABLED)
        os.write(self.master, self.response.buffer)

    def __call__(self) -> None:
        os.readv(self.master, [self.request])
        self.prepare()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=10_000, help="cycles per batch (and for tracemalloc)")
    parser.add_argument("--rounds", type=int, default=5, help="batches of each contender (medians)")
    add_output_options(parser)
    args = parser.parse_args()
    master, slave, path = pty_line()
    device = build_device("serial", "bench", {"port": path, "commands": COMMANDS, "readings": READINGS,
                                              "timeout_ms": 100.0}, "bench")
    device.check()
    device.configure()
    responder = Responder(master, device)
    u, y = np.array([3.5, 0.0]), np.zeros(len(READINGS))
    request = bytes(Frame(REQUEST_SYNC, len(COMMANDS)).buffer)
    answer = bytearray(len(responder.response.buffer))
    view = memoryview(answer)
    poller = select.poll()
    poller.register(device.fd, select.POLLIN)
    line = device._line

    def with_device() -> None:
        device.write(u)
        device.read(y)

    def os_calls() -> None:
        os.write(device.fd, request)
        got = 0
        while got < len(answer):
            poller.poll(100)
            got += os.readv(device.fd, [view[got:]])

    def pyserial_calls() -> None:
        line.write(request)
        line.read(len(answer))

    task_u, task_y = np.zeros(len(READINGS)), np.array([3.5, 0.0])
    wiring = DeviceWiring(device, "let", (CommandLimit(-24, 24, 0, 1e5), CommandLimit(0, 1, 1)),
                          ((slice(0, 2), slice(0, 2)),), ((slice(0, 3), slice(0, 3)),))
    devices = TaskDevices("bench", 1_000_000, [wiring], task_u, task_y)
    devices.configured = list(devices.slots)  # configured above; at_release is what is timed
    cycle = [0]

    def framework() -> None:
        devices.at_release(cycle[0])
        cycle[0] += 1

    responder.prepare()
    results = {
        "device vs os calls": compare(with_device, os_calls, responder, args.cycles, args.rounds),
        "device vs pyserial": compare(with_device, pyserial_calls, responder, args.cycles, args.rounds),
        "framework vs os calls": compare(framework, os_calls, responder, args.cycles, args.rounds),
    }
    assert list(y) == [123.25, 1.5, 40.0] and list(task_u) == [123.25, 1.5, 40.0], (y, task_u)

    def framework_and_drive() -> None:
        framework()
        responder()

    grown, grown_all = bytes_kept(framework_and_drive, 2000, args.cycles)
    devices.stop()

    where = where_measured()
    print(f"# bench_serial: {where}; {args.rounds} x {args.cycles} cycles each, medians; pty, responder untimed\n")
    print("| contenders | ours µs | bare µs | ratio | 1.3 x bare + 1 µs | within |")
    print("|---|---:|---:|---:|---:|---|")
    for name, r in results.items():
        print(f"| {name} | {r['driver_us']:.2f} | {r['bare_us']:.2f} | {r['ratio']:.2f} | {r['target_us']:.2f} | "
              f"{'yes' if r['within_target'] else 'no'} |")
    print(f"\nallocation over {args.cycles} cycles of at_release (guard + exchange + copies): "
          f"{grown} bytes kept by rtloop/io, {grown_all} bytes by everything in the process (tracemalloc)")
    if args.json:
        write_json(args.json, {"where": where, "cycles": args.cycles, "results": results,
                               "allocated_bytes_io": grown, "allocated_bytes_all": grown_all})
    os.close(master)
    os.close(slave)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
