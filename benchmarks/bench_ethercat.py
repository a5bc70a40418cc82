"""One EtherCAT process-data cycle through rtloop next to the same LRW frame on a bare raw socket and
next to pysoem's own ``send_processdata``/``receive_processdata``, in one run; and what the device
loop allocates (tracemalloc over 10,000 cycles). Needs root: it makes a veth pair of its own.

Two emulated CiA 402 drives (``io/drives/esc.py``) answer on the other end of the pair, *in this
process and between the timed halves of a cycle* (untimed, as real slaves answer while the frame
is on the wire): the figures are the host's share of a cycle, not the emulator's Python. Timed:

- ``rtloop``  ``EthercatDevice.write(u)`` + ``read(y)``: controlwords from the CiA 402 state machine,
              targets in counts, the outputs packed into the prebuilt frame, ``send``; then
              ``recv_into``, index and working counter checked, the inputs unpacked into SI readings;
- ``bare``    the same frame's bytes: ``send``, then ``recv_into`` on the same socket;
- ``pysoem``  ``send_processdata()`` then ``receive_processdata(timeout)`` (SOEM's own, through
              pysoem's Cython; its outputs are not even filled in).

Usage::

    sudo python benchmarks/bench_ethercat.py                        # 5 x 10,000 cycles each
    sudo python benchmarks/bench_ethercat.py --cycles 1000 --rounds 2 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import struct
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable

import numpy as np

from rtloop.io.device import build_device
from rtloop.io.drives.drive_model import DriveModel
from rtloop.io.drives.emulator import DEFAULT_IDENTITY
from rtloop.io.drives.esc import EmulatedSlave, Segment
from rtloop.io.drives.pdo import DEFAULT_RXPDO, DEFAULT_TXPDO, PdoLayout
from rtloop.io.drives.rawsocket import FRAME_BYTES, open_raw
from rtloop.io.host import DeviceWiring, TaskDevices

JOINT = {"vendor": DEFAULT_IDENTITY.vendor, "product": DEFAULT_IDENTITY.product,
         "revision": DEFAULT_IDENTITY.revision, "mode": "csp", "counts_per_rev": 4096}


class InlineSlaves:
    """Two emulated slaves on the slave end, answering one frame when asked (between timed halves).

    SOEM configures the bus against an emulator process (``python -m rtloop.io.drives.emulator``);
    these slaves are then set up as SOEM left that one (station addresses, sync managers, FMMUs in
    SOEM's layout: every slave's outputs, then every slave's inputs; OP) and take its place."""

    def __init__(self, interface: str) -> None:
        self.segment = Segment([EmulatedSlave(i, DEFAULT_IDENTITY, PdoLayout(DEFAULT_RXPDO), PdoLayout(DEFAULT_TXPDO),
                                              DriveModel()) for i in (1, 2)])
        self.sock = open_raw(interface, timeout_s=1.0)
        self.buffer = bytearray(FRAME_BYTES + 64)
        slaves = self.segment.slaves
        out_total = sum(slave.rx.size for slave in slaves)
        out_at, in_at = 0, out_total
        for slave in slaves:
            rx, tx, m = slave.rx.size, slave.tx.size, slave.memory
            struct.pack_into("<H", m, 0x0010, 0x1000 + slave.position)
            struct.pack_into("<HHBBBBHHBBBB", m, 0x0800, 0x1000, rx, 0x64, 0, 1, 0, 0x1200, tx, 0x20, 0, 1, 0)
            struct.pack_into("<IHBBHBBB", m, 0x0600, out_at, rx, 0, 7, 0x1000, 0, 2, 1)
            struct.pack_into("<IHBBHBBB", m, 0x0610, in_at, tx, 0, 7, 0x1200, 0, 1, 1)
            struct.pack_into("<H", m, 0x0420, 0)  # no watchdog: the benchmark pauses between its phases
            struct.pack_into("<H", m, 0x0130, 8)
            out_at += rx
            in_at += tx

    def answer(self) -> None:
        size = self.sock.recv_into(self.buffer)
        frame = self.buffer[:size]
        self.segment.process(frame)
        self.sock.send(frame)


def configure_against_a_process(slave_if: str, configure: Callable[[], None]) -> None:
    """Run ``configure`` (SOEM's scan and mapping) while an emulator process answers on ``slave_if``."""
    with tempfile.NamedTemporaryFile("r", suffix=".log") as log:
        process = subprocess.Popen([sys.executable, "-m", "rtloop.io.drives.emulator", "--interface", slave_if,
                                    "--slaves", "2", "--log", log.name])
        try:
            deadline = time.monotonic() + 30.0
            while "emulating" not in log.read() and time.monotonic() < deadline:  # its socket is open
                time.sleep(0.05)
            configure()
        finally:
            process.terminate()
            process.wait()


def timed(first: Callable[[], None], answer: Callable[[], None], second: Callable[[], None], cycles: int) -> np.ndarray:
    """ns of ``first`` + ``second``, cycle by cycle, the slaves' ``answer`` between them untimed."""
    clock = time.perf_counter_ns
    took = np.zeros(cycles, dtype=np.int64)
    for i in range(cycles):
        start = clock()
        first()
        middle = clock()
        answer()
        resume = clock()
        second()
        took[i] = middle - start + clock() - resume
    return took


def veth() -> tuple[str, str]:
    tag = f"{os.getpid() % 100000:05d}"
    master, slave = f"ebm{tag}", f"ebs{tag}"
    subprocess.run(["ip", "link", "add", master, "type", "veth", "peer", "name", slave], check=True)
    for name in (master, slave):
        subprocess.run(["ip", "link", "set", name, "up"], check=True)
    return master, slave


def bench_pysoem(master_if: str, slave_if: str, cycles: int, rounds: int) -> list[np.ndarray]:
    import pysoem

    master = pysoem.Master()
    master.open(master_if)

    def configure() -> None:
        assert master.config_init() == 2
        master.config_map()
        master.state_check(pysoem.SAFEOP_STATE, 2_000_000)
        master.state = pysoem.OP_STATE
        master.write_state()
        for _ in range(200):
            master.send_processdata()
            master.receive_processdata(2000)
            if master.state_check(pysoem.OP_STATE, 5000) == pysoem.OP_STATE:
                break

    try:
        configure_against_a_process(slave_if, configure)
        slaves = InlineSlaves(slave_if)
        return [timed(master.send_processdata, slaves.answer, lambda: master.receive_processdata(20_000), cycles)
                for _ in range(rounds)]
    finally:
        master.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cycles", type=int, default=10_000)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("bench_ethercat: needs root (a veth pair, raw sockets)", file=sys.stderr)
        return 2
    master_if, slave_if = veth()
    try:
        pysoem_ns = bench_pysoem(master_if, slave_if, args.cycles, args.rounds)
        joints = [{"name": name, **JOINT} for name in ("a", "b")]
        # the answer's time counts against timeout_us (from the send), and here it is the inline
        # emulator's Python: a wide timeout, so that a loaded host does not end the benchmark
        device = build_device("ethercat", "drives", {"interface": master_if, "joints": joints, "timeout_us": 1e6},
                              "bench")
        configure_against_a_process(slave_if, device.configure)  # to OP, the process data kept flowing until T0
        device._stop_keeper()  # here, before the inline slaves listen (they are in OP already)
        device.activate()
        slaves = InlineSlaves(slave_if)
        u, y = np.zeros(device.n_inputs), np.zeros(device.n_outputs)
        for _ in range(20):  # the slaves to OP, the drives enabled
            device.write(u)
            device._send_outputs()
            slaves.answer()
            device._take_answer(y)
        assert device.cycle.enabled

        def rtloop_first() -> None:
            device.write(u)
            device._send_outputs()

        sock, frame, reply = device.socket, device._frame, device._reply
        rtloop_ns, bare_ns = [], []
        for _ in range(args.rounds):  # interleaved rounds: the same conditions for both
            rtloop_ns.append(timed(rtloop_first, slaves.answer, lambda: device._take_answer(y), args.cycles))
            bare_ns.append(timed(lambda: sock.send(frame), slaves.answer, lambda: sock.recv_into(reply), args.cycles))
        # allocation: the whole per-cycle work of the task's devices, 10,000 cycles
        wiring = DeviceWiring(device, "let", tuple(device.default_limits().values()), (), ())
        devices = TaskDevices("bench", 1_000_000, [wiring], np.zeros(4), np.zeros(4))
        slot = devices.slots[0]
        devices.active = True
        devices.configured = [slot]

        def at_release() -> None:
            slot.send("bench", 0)
            device._send_outputs()

        for _ in range(200):
            at_release()
            slaves.answer()
            device._take_answer(slot.y)
        tracemalloc.start()
        before = tracemalloc.take_snapshot()
        for _ in range(10_000):
            at_release()
            slaves.answer()
            device._take_answer(slot.y)
        after = tracemalloc.take_snapshot()
        tracemalloc.stop()
        if os.environ.get("BENCH_SHOW_KEPT"):
            for stat in after.compare_to(before, "lineno")[:8]:
                print(stat, file=sys.stderr)
        device_side = ("drives/cycle.py", "drives/ethercat.py", "drives/cia402.py", "io/host.py", "io/limits.py")
        kept_io = sum(s.size_diff for s in after.compare_to(before, "filename")  # not the emulated slaves' share
                      if any(name in str(s.traceback) for name in device_side) and s.size_diff > 0)
        kept_all = sum(s.size_diff for s in after.compare_to(before, "filename") if s.size_diff > 0)
        device.write_safe(u)
        device.close()
    finally:
        subprocess.run(["ip", "link", "del", master_if], capture_output=True)
    # the median cycle (a loaded host's preemptions land in a few cycles of either contender), and
    # each contender's fastest round's mean
    r, b, p = (float(np.median(np.concatenate(samples))) / 1000 for samples in (rtloop_ns, bare_ns, pysoem_ns))
    result = {"rtloop_median_us": r, "bare_median_us": b, "pysoem_median_us": p, "ratio_to_bare": r / b,
              "target_us": 1.3 * b + 1.0, "within_target": r <= 1.3 * b + 1.0, "ratio_to_pysoem": r / p,
              "rtloop_best_mean_us": min(float(t.mean()) for t in rtloop_ns) / 1000,
              "bare_best_mean_us": min(float(t.mean()) for t in bare_ns) / 1000,
              "pysoem_best_mean_us": min(float(t.mean()) for t in pysoem_ns) / 1000,
              "kept_bytes_device": kept_io, "kept_bytes_process": kept_all, "cycles": args.cycles,
              "rounds": args.rounds, "machine": platform.machine(), "load": os.getloadavg()[0]}
    print(json.dumps(result, indent=1))
    if args.json:
        with open(args.json, "w") as out:
            json.dump(result, out, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
