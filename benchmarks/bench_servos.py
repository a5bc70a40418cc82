"""One sync write + sync read cycle of six Dynamixel servos through rtloop, next to the same two packets
with bare os calls and next to dynamixel-sdk's GroupSyncWrite/GroupSyncRead, in one run; and what the
cycle allocates (tracemalloc).

A pseudo-terminal stands in for the bus; a child process on its master side answers each sync read
request with the six status packets at once (made once by the servo model: 6 × XM430-W350, present
current, velocity and position, 10 bytes each, 21-byte status packets). The answers cannot wait in
place before a cycle, as a benchmark of one request and one answer could have them: dynamixel-sdk
flushes the input before it sends (``clearPort``), so every contender pays the same round trip
through the pty and the child. Contenders, interleaved in batches:

- ``rtloop``      ``DynamixelBus.write(u)`` + ``read(y)``: 6 goals in rad converted, rounded, clamped
                  into the sync write packet built once, its CRC-16 (stuffing checked); the sync read
                  sent, 6 status packets scanned, CRC-checked, their data converted to SI;
- ``os calls``    the same two packets, prepared beforehand: two ``os.write``, then ``poll`` +
                  ``os.readv`` until the 126 bytes of the answers are in (no packet built, none checked);
- ``dynamixel-sdk``  ROBOTIS's Python SDK as its examples use it: ``changeParam`` for each servo,
                  ``GroupSyncWrite.txPacket()``, ``GroupSyncRead.txRxPacket()``, then ``getData`` of
                  the three fields of each servo (raw integers: no conversion to SI);
- ``framework``   ``TaskDevices.at_release`` with the bus: the guard, the copies, then the cycle;
- ``Python refs`` the rtloop contender with the packets' CRC-16 sealed and the answers scanned and
                  checked by the Python references instead of ``io/devio_c/servo.c`` (batches
                  interleaved with the others);
- ``host share``  the rtloop cycle on a line that hands back the six answers at once (no pty, no
                  other process): the C part against the Python references, the host's own work.

Usage::

    python benchmarks/bench_servos.py                 # 5 x 2,000 cycles each
    python benchmarks/bench_servos.py --cycles 300 --rounds 1 --without-sdk --json out.json
"""

from __future__ import annotations

import argparse
import os
import select
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parents[1] / "tests"))
from _common import add_output_options, where_measured, write_json
from bench_devices import bytes_kept, compare, pty_line

from rtloop.io.device import build_device
from rtloop.io.host import DeviceWiring, TaskDevices
from rtloop.io.servos.line import ModelLine, PortLine
from rtloop.io.servos.model import build_bus
from rtloop.io.servos.protocol import PROTOCOLS
from servo_lines import servos_answering_at_once

IDS = [1, 2, 3, 4, 5, 6]
SERVOS = [{"name": f"joint{i}", "id": i, "model": "XM430-W350", "range_rad": [-1.5, 1.5]} for i in IDS]


def serve_answers(master: int, request: bytes, answers: bytes) -> None:
    """The servos, in a child process: whenever a sync read request has come, its six answers go out."""
    seen = bytearray()
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:
            os._exit(0)
        seen += data
        at = seen.find(request)
        if at >= 0:
            del seen[:at + len(request)]
            os.write(master, answers)
        elif len(seen) > 4 * len(request):
            del seen[:-len(request)]


def nothing() -> None:
    """Between timed cycles: the servos answer by themselves (another process)."""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=2_000, help="cycles per batch (and for tracemalloc)")
    parser.add_argument("--rounds", type=int, default=5, help="batches of each contender")
    add_output_options(parser)
    parser.add_argument("--without-sdk", action="store_true", help="leave dynamixel-sdk out (the test's quick run)")
    args = parser.parse_args()
    import serial

    master, slave, path = pty_line()
    device = build_device("dynamixel", "bench", {"port": path, "servos": SERVOS, "timeout_ms": 100.0,
                                                   "on_missing": "stale", "max_stale_in_a_row": 1_000_000}, "bench")
    bus = build_bus("dynamixel", IDS, ["XM430-W350"], 0.002)
    device.attach(ModelLine(bus))  # set-up against the model in process; the cycles then go over the pty
    device.activate()
    answers = bus.receive(bytes(device.state.request))
    port = serial.Serial(path, 1_000_000, timeout=0, write_timeout=0)
    device.line = PortLine(port.fileno())
    responder = os.fork()
    if responder == 0:
        os.close(slave)  # the slave is the parent's only: when it ends, the child reads EIO and ends too
        port.close()
        serve_answers(master, bytes(device.state.request), answers)
    u, y = np.full(6, 0.25), np.zeros(device.n_outputs)
    device.write(u)
    sync_write = bytes(device.goals.seal())
    sync_read = bytes(device.state.request)
    answer = bytearray(len(answers))
    view = memoryview(answer)
    poller = select.poll()
    poller.register(port.fileno(), select.POLLIN)
    fd = port.fileno()

    def with_rtloop() -> None:
        device.write(u)
        device.read(y)

    def os_calls() -> None:
        os.write(fd, sync_write)
        os.write(fd, sync_read)
        got = 0
        while got < len(answer):
            poller.poll(100)
            got += os.readv(fd, [view[got:]])

    results = {}
    try:
        import dynamixel_sdk as sdk
    except ImportError:
        sdk = None
    if args.without_sdk:
        sdk = None
    if sdk is not None:
        handler = sdk.PortHandler(path)
        handler.openPort()
        handler.setBaudRate(1_000_000)
        packets = sdk.Protocol2PacketHandler()
        group_write = sdk.GroupSyncWrite(handler, packets, 116, 4)
        group_read = sdk.GroupSyncRead(handler, packets, 126, 10)
        goal = list((2048 + 163).to_bytes(4, "little"))
        for servo_id in IDS:
            group_write.addParam(servo_id, goal)
            group_read.addParam(servo_id)
        sdk_values = [0] * 18
        sdk_failures = [0]

        def with_sdk() -> None:
            for servo_id in IDS:
                group_write.changeParam(servo_id, goal)
            group_write.txPacket()
            if group_read.txRxPacket() != sdk.COMM_SUCCESS:  # its 34 ms timeout, on a loaded machine
                sdk_failures[0] += 1
                return
            for index, servo_id in enumerate(IDS):
                sdk_values[3 * index] = group_read.getData(servo_id, 126, 2)
                sdk_values[3 * index + 1] = group_read.getData(servo_id, 128, 4)
                sdk_values[3 * index + 2] = group_read.getData(servo_id, 132, 4)

        results["rtloop vs dynamixel-sdk"] = compare(with_rtloop, with_sdk, nothing, args.cycles, args.rounds)
    task_u, task_y = np.zeros(device.n_outputs), np.full(6, 0.25)
    limits = tuple(device.default_limits().values())
    wiring = DeviceWiring(device, "let", limits, ((slice(0, 6), slice(0, 6)),),
                          ((slice(0, device.n_outputs), slice(0, device.n_outputs)),))
    devices = TaskDevices("bench", 2_000_000, [wiring], task_u, task_y)
    devices.configured = list(devices.slots)  # set up above; at_release is what is timed
    cycle = [0]

    def framework() -> None:
        devices.at_release(cycle[0])
        cycle[0] += 1

    compiled_protocol, compiled_take = device.state.protocol, device.state.take
    checks_in_c = compiled_protocol is not PROTOCOLS["dynamixel"]

    def use_python(bus: Any, python: bool) -> None:
        """The bus's packets sealed and its answers scanned by the Python references, or in C again."""
        bus.goals.protocol = bus.state.protocol = PROTOCOLS["dynamixel"] if python else compiled_protocol
        bus.state.take = None if python else compiled_take

    def python_references(python: bool) -> None:
        use_python(device, python)

    results["rtloop vs os calls"] = compare(with_rtloop, os_calls, nothing, args.cycles, args.rounds,
                                            python_references if checks_in_c else None)
    results["framework vs os calls"] = compare(framework, os_calls, nothing, args.cycles, args.rounds)
    host = servos_answering_at_once("dynamixel", "host", SERVOS)
    host_y = np.zeros(host.n_outputs)

    def host_share() -> None:
        host.write(u)
        host.read(host_y)

    def host_share_python() -> None:
        use_python(host, True)
        try:
            host_share()
        finally:
            use_python(host, False)

    if checks_in_c:
        results["host share: C part vs Python references"] = compare(host_share, host_share_python, nothing,
                                                                       args.cycles, args.rounds)
    assert abs(y[0] - 0.0) < 1.0 and np.all(np.isfinite(y)), y

    grown, _grown_all = bytes_kept(framework, 500, args.cycles)

    failures = sdk_failures[0] if sdk is not None else 0
    where = where_measured()
    print(f"# bench_servos: {where}; {args.rounds} x {args.cycles} cycles each, fastest batch (medians); "
          "pty, responder untimed\n")
    print("| contenders | ours µs | theirs µs | ratio | ours median µs | theirs median µs | Python refs µs (ratio) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, r in results.items():
        python = f"{r['reference_us']:.1f} ({r['reference_ratio']:.2f})" if "reference_us" in r else ""
        print(f"| {name} | {r['driver_us']:.1f} | {r['bare_us']:.1f} | {r['ratio']:.2f} | "
              f"{r['driver_median_us']:.1f} | {r['bare_median_us']:.1f} | {python} |")
    print(f"\nallocation over {args.cycles} cycles of at_release (guard + sync write + sync read + copies): "
          f"{grown} bytes kept by rtloop/io (tracemalloc)")
    print(f"sync reads that timed out: dynamixel-sdk {failures}, rtloop {device.stale_reads}")
    if not checks_in_c:
        print("the CRC-16 ran as the Python references (io/_devio.c not built, or RTLOOP_PURE_PYTHON=1)")
    if args.json:
        write_json(args.json, {"where": where, "cycles": args.cycles, "results": results, "allocated_bytes_io": grown,
                               "sdk_failures": failures, "rtloop_stale_reads": device.stale_reads,
                               "checks_in_c": checks_in_c})
    port.close()
    os.kill(responder, 9)
    os.waitpid(responder, 0)
    os.close(master)
    os.close(slave)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
