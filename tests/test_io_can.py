"""CAN driver on vcan0 and on the emulated kvaser_pci pair (can0 ↔ can1) in the test guest."""

from __future__ import annotations

import csv
import json
import socket
import struct
import threading
import time

import numpy as np
import pytest

from can_pair import attach_to_a_pair, wire_frame
from conftest import scaled_ns, scaled_s
from io_guest_devices import KEPT_BYTES_ALLOWED, bytes_kept_by, guest_device
from rtloop.errors import DeviceError, DeviceFault
from rtloop.io.device import build_device

SEND = [{"id": 0x200, "signals": [{"name": "torque", "start_byte": 0, "type": "i16", "scale": 0.01},
                                  {"name": "mode", "start_byte": 2, "type": "u8"}]}]
RECEIVE = [{"id": 0x180, "timeout_ms": 50, "signals": [{"name": "position", "start_byte": 0, "type": "i32",
                                                       "scale": 1e-3}]}]


def raw_socket(interface, fd=False):
    sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    if fd:
        sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FD_FRAMES, 1)
    sock.bind((interface,))
    sock.settimeout(5.0)
    return sock


def drive(interface, **settings):
    table = {"interface": interface, "send": SEND, "receive": RECEIVE, "heartbeat": {"id": 0x700}, **settings}
    return build_device("can", "drive", table, "app.toml")


@pytest.mark.rtkernel
@pytest.mark.parametrize("bus", ["vcan", "can"])
def test_frames_go_out_every_cycle_with_the_heartbeat_and_come_in(bus):
    entry = guest_device(bus)
    ours, theirs = (entry["interface"], entry["interface"]) if bus == "vcan" else entry["interfaces"]
    device = drive(ours)
    device.check()
    peer = raw_socket(theirs)
    device.configure()
    try:
        y = np.zeros(1)
        for cycle in range(3):
            device.write(np.array([-1.5 + cycle, 3.0]))
            command = peer.recv(16)
            assert struct.unpack_from("=IB", command) == (0x200, 8)
            assert struct.unpack_from("<hB", command, 8) == (-150 + 100 * cycle, 3)
            beat = peer.recv(16)
            assert struct.unpack_from("=IB", beat) == (0x700, 1) and beat[8] == cycle
            peer.send(wire_frame(0x180, struct.pack("<i", 1234 + cycle)))
            device.read(y)
            assert y[0] == pytest.approx(1.234 + cycle * 1e-3)
    finally:
        device.close()
        peer.close()


@pytest.mark.rtkernel
def test_a_missing_frame_is_a_fault_or_a_stale_read():
    entry = guest_device("vcan")
    device = drive(entry["interface"])
    device.configure()
    try:
        with pytest.raises(DeviceFault, match=r"devices\.drive\.receive\[0\] \(id 0x180\): no frame within 50 ms"):
            device.read(np.zeros(1))
    finally:
        device.close()
    stale = drive(entry["interface"], receive=[{**RECEIVE[0], "on_missing": "stale"}])
    stale.configure()
    peer = raw_socket(entry["interface"])
    try:
        y = np.zeros(1)
        peer.send(wire_frame(0x180, struct.pack("<i", 42)))
        stale.read(y)
        stale.read(y)  # nothing new: the last value stays, counted
        assert y[0] == pytest.approx(0.042) and stale.stale_reads == 1
    finally:
        stale.close()
        peer.close()


@pytest.mark.rtkernel
def test_the_newest_frame_of_an_id_wins_and_other_ids_are_filtered_out():
    entry = guest_device("vcan")
    device = drive(entry["interface"])
    device.configure()
    peer = raw_socket(entry["interface"])
    try:
        for value in (1, 2, 3):
            peer.send(wire_frame(0x180, struct.pack("<i", value)))
        peer.send(wire_frame(0x181, struct.pack("<i", 99)))
        y = np.zeros(1)
        device.read(y)
        assert y[0] == pytest.approx(0.003)
    finally:
        device.close()
        peer.close()


@pytest.mark.rtkernel
def test_fd_frames_on_vcan():
    entry = guest_device("vcan")
    signals = [{"name": f"s{i}", "start_byte": 8 * i, "type": "f64"} for i in range(8)]
    device = build_device("can", "fd", {"interface": entry["interface"], "fd": True,
                                        "send": [{"id": 0x300, "length": 64, "signals": signals}]}, "app.toml")
    device.check()
    peer = raw_socket(entry["interface"], fd=True)
    device.configure()
    try:
        values = np.arange(8) * 1.25
        device.write(values)
        received = peer.recv(72)
        assert len(received) == 72 and struct.unpack_from("=IB", received) == (0x300, 64)
        assert struct.unpack_from("<8d", received, 8) == tuple(values)
    finally:
        device.close()
        peer.close()


@pytest.mark.rtkernel
def test_a_missing_interface_is_one_line():
    guest_device("vcan")
    with pytest.raises(DeviceError, match=r"devices\.drive\.interface: no network interface 'can7' \(CAN interfaces "
                                          r"here: .*vcan0"):
        drive("can7").check()


@pytest.mark.rtkernel
def test_no_allocation_in_the_loop():
    entry = guest_device("vcan")
    device = drive(entry["interface"])
    device.configure()
    peer = raw_socket(entry["interface"])
    answer = bytearray(wire_frame(0x180, struct.pack("<i", 7)))
    incoming = bytearray(16)
    try:
        u, y = np.array([0.5, 1.0]), np.zeros(1)

        def cycle():
            device.write(u)
            peer.recv_into(incoming)  # the command
            peer.recv_into(incoming)  # the heartbeat
            peer.send(answer)
            device.read(y)

        assert bytes_kept_by(cycle, 10_000) <= KEPT_BYTES_ALLOWED
        assert y[0] == pytest.approx(0.007)
    finally:
        device.close()
        peer.close()


def test_the_driver_loop_over_a_unix_socket_pair_allocates_nothing():
    """Anywhere: the driver's own per-cycle work, over the same socket calls (send, poll, recv_into)
    on a UNIX datagram pair in place of a CAN socket (this kernel may have no CAN)."""
    device = drive("vcan0")
    peer = attach_to_a_pair(device)
    answer = bytearray(wire_frame(0x180, struct.pack("<i", -9)))
    incoming = bytearray(72)
    try:
        u, y = np.array([0.5, 1.0]), np.zeros(1)

        def cycle():
            device.write(u)
            peer.recv_into(incoming)
            peer.recv_into(incoming)
            peer.send(answer)
            device.read(y)

        assert bytes_kept_by(cycle, 10_000) <= KEPT_BYTES_ALLOWED
        assert y[0] == pytest.approx(-0.009)
        assert struct.unpack_from("=IB", incoming) == (0x700, 1)  # the cycle's last frame: the heartbeat
        assert incoming[8] == (2_000 + 10_000 - 1) & 0xFF
    finally:
        device.close()
        peer.close()


def test_a_drive_that_answers_every_command_is_read_in_the_cycle_of_the_command():
    """Anywhere (a UNIX socket pair in place of the bus): a drive answering each command frame, a
    little later, as a separate process does. Nothing goes out before T0 (an answer to a frame sent
    at configure, arriving after activate, would be taken for cycle 0's reading and make every
    reading after it one cycle late); at the end the safe frame goes out with the heartbeat."""
    device = drive("vcan0", receive=[{**RECEIVE[0], "timeout_ms": 5000}])
    peer = attach_to_a_pair(device)
    seen: list[tuple[int, bytes]] = []

    def answer_each_command() -> None:  # torque × 10 back as the position, after a moment
        while True:
            try:
                data = peer.recv(72)
            except OSError:
                return
            if not data:
                return
            can_id = struct.unpack_from("=I", data)[0]
            seen.append((can_id, data[8:16]))
            if can_id == 0x200:
                time.sleep(0.02)
                torque = struct.unpack_from("<h", data, 8)[0]
                peer.send(wire_frame(0x180, struct.pack("<i", torque * 10)))

    responder = threading.Thread(target=answer_each_command, daemon=True)
    responder.start()
    try:
        device.write_safe(np.array([-0.5, 0.0]))  # what configure does: nothing may leave before T0
        device.activate()  # T0 comes before a slow drive's answer would
        y = np.zeros(1)
        for cycle in range(6):
            device.write(np.array([0.25 * (cycle + 1), 1.0]))
            device.read(y)
            assert y[0] == pytest.approx(0.25 * (cycle + 1)), cycle  # this cycle's answer, not the one before
        assert struct.unpack_from("<h", seen[0][1])[0] == 25  # the first frame out was cycle 0's
        device.write_safe(np.array([-0.5, 0.0]))
        deadline = time.monotonic() + 30  # the responder's thread takes both frames (a loaded machine: late)
        while not (len(seen) >= 2 and seen[-1][0] == 0x700 and seen[-2][0] == 0x200
                   and struct.unpack_from("<h", seen[-2][1])[0] == -50) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert seen[-2][0] == 0x200 and struct.unpack_from("<h", seen[-2][1])[0] == -50  # the safe torque
        assert seen[-1][0] == 0x700  # and the heartbeat
    finally:
        device.close()
        peer.shutdown(socket.SHUT_RDWR)
        peer.close()
        responder.join(timeout=5)


def task_devices_on_a_pair(device):
    """A task's devices (``TaskDevices``) holding ``device`` alone, already on its socket pair: its
    commands from the task's y[0:2] (torque, mode; limits wider than the tests drive them), its
    position into the task's u[0] (returned with them)."""
    from rtloop.io.device import CommandLimit
    from rtloop.io.host import DeviceWiring, TaskDevices

    device.configure = lambda: None  # attached to the pair already (this kernel may have no CAN)
    limits = (CommandLimit(-100.0, 100.0, 0.0), CommandLimit(0.0, 255.0, 0.0))
    task_u, task_y = np.zeros(1), np.zeros(2)
    wiring = DeviceWiring(device, "let", limits, ((slice(0, 2), slice(0, 2)),), ((slice(0, 1), slice(0, 1)),))
    return TaskDevices("ctl", 1_000_000, [wiring], task_u, task_y), task_u


def test_a_frame_that_does_not_come_in_time_is_a_stale_read_counted_with_its_cycle_and_lag():
    """Anywhere (a UNIX socket pair in place of the bus): with on_missing = "stale", a cycle whose
    answer has not come within its timeout keeps the last values; the task's devices count the cycle,
    keep it among the first stale cycles, and the longest run of stale cycles in a row (the lag)."""
    device = drive("vcan0", receive=[{**RECEIVE[0], "timeout_ms": 1, "on_missing": "stale"}])
    peer = attach_to_a_pair(device)
    devices, task_u = task_devices_on_a_pair(device)
    lost = {3, 4, 7}  # the drive's answers to these cycles never come
    seen = []
    try:
        devices.configure()
        devices.activate()
        for cycle in range(10):
            if cycle not in lost:
                peer.send(wire_frame(0x180, struct.pack("<i", 1000 * cycle)))  # the position this cycle reads
            devices.at_release(cycle)
            seen.append(task_u[0])
    finally:
        devices.stop()
        peer.close()
    assert seen == [0.0, 1.0, 2.0, 2.0, 2.0, 5.0, 6.0, 6.0, 8.0, 9.0]  # the stale cycles kept the last values
    assert devices.stale_report() == {"drive": {
        "kind": "can", "stale_reads": 3, "stale_cycles": 3, "longest_lag_cycles": 2, "first_stale_cycles": [3, 4, 7],
        "stale_reads_by_source": {"receive[0] (id 0x180)": 3}, "clamped_cycles": {}, "rate_limited_cycles": {}}}


def test_counting_stale_reads_allocates_nothing_that_stays():
    """10,000 cycles of TaskDevices.at_release with a CAN device that reads stale every other cycle."""
    device = drive("vcan0", receive=[{**RECEIVE[0], "timeout_ms": 0.001, "on_missing": "stale"}])
    peer = attach_to_a_pair(device)
    devices, _task_u = task_devices_on_a_pair(device)
    answer, incoming, cycle = bytearray(wire_frame(0x180, struct.pack("<i", 7))), bytearray(72), [0]

    def one_cycle():
        if cycle[0] & 1:
            peer.send(answer)
        devices.at_release(cycle[0])
        peer.recv_into(incoming)  # the command frame and the heartbeat, taken off the pair
        peer.recv_into(incoming)
        cycle[0] += 1

    try:
        devices.configure()
        devices.activate()
        assert bytes_kept_by(one_cycle, 10_000) <= KEPT_BYTES_ALLOWED
    finally:
        devices.stop()
        peer.close()
    report = devices.stale_report()["drive"]
    assert report["stale_cycles"] == 6_000 and report["longest_lag_cycles"] == 1  # 12,000 cycles, every other


PEER = """
import os, socket, struct, sys
os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(70))  # answers in time, as a drive does
lost = {float(v) for v in sys.argv[2].split(",")}
bus = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
bus.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, struct.pack("=II", 0x210, 0x7FF | 0x80000000))
bus.bind((sys.argv[1],))
print("ready", flush=True)
while True:
    can_id, _, data = struct.unpack("=IB3x8s", bus.recv(16))
    if struct.unpack("<d", data)[0] not in lost:  # the answers to these commands never come
        bus.send(struct.pack("=IB3x8s", 0x190, 8, data))
"""


@pytest.mark.rtkernel
@pytest.mark.timeout(scaled_s(120))
def test_a_run_counts_its_stale_reads_per_cycle_in_summary_json_and_replay_says_them(tmp_path):
    """A real-time run on vcan0 against a drive (a separate process) that echoes each command frame
    but never answers those of cycles 5, 6 and 12: with on_missing = "stale" those cycles keep the
    last values; summary.json counts them (cycles, lag, frame), the comparison with the simulation
    ends before the first, and the replay plays them back and says so."""
    import os
    import subprocess
    import sys

    import rtloop
    from device_test_drivers import CycleAndReading, MirrorTwin
    from replay_helpers import compare_signals, first_miss_s
    from rtloop import App
    from rtloop.runtime.replay import replay

    entry = guest_device("vcan")
    period_ns, lost = scaled_ns(10_000_000), [5, 6, 12]

    def app(name):
        app = App(f"{name}_{os.getpid()}")
        ctl = app.add_task("ctl", CycleAndReading(), period_ns=period_ns)
        dev = app.add_device(
            "drive", "can", task="ctl", interface=entry["interface"], twin=MirrorTwin(1, 1.0),
            send=[{"id": 0x210, "signals": [{"name": "command", "start_byte": 0, "type": "f64"}]}],
            receive=[{"id": 0x190, "timeout_ms": period_ns / 2e6, "on_missing": "stale",
                      "signals": [{"name": "position", "start_byte": 0, "type": "f64"}]}],
            limits={"command": {"min": -1e6, "max": 1e6, "safe": 0.0}})
        app.connect(ctl.y[0], dev.u[0])  # the command written at release k is k (let)
        app.connect(dev.y[0], ctl.u[0])  # the drive's echo of it: k, read in cycle k
        app.record(ctl.u, ctl.y)
        return app

    peer = subprocess.Popen([sys.executable, "-c", PEER, entry["interface"], ",".join(map(str, lost))],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert peer.stdout.readline().strip() == "ready"
        rtloop.run(app("can_stale"), 20 * period_ns / 1e9, tmp_path / "run")
    finally:
        peer.kill()
        peer.communicate()  # reaped, its pipe closed
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    report = summary["devices"]["drive"]
    stale = report["first_stale_cycles"]
    assert set(lost) <= set(stale), report  # a loaded guest may add one; never miss one
    assert report["task"] == "ctl" and report["kind"] == "can"
    assert report["stale_reads"] == report["stale_cycles"] == len(stale)  # one frame, once per cycle
    assert report["stale_reads_by_source"] == {"receive[0] (id 0x190)": len(stale)}
    assert report["longest_lag_cycles"] >= 2  # cycles 5 and 6 in a row
    assert any(note.startswith(f"device 'drive' (task ctl): {len(stale)} stale device reads")
               for note in summary["notes"])
    with open(tmp_path / "run" / "signals.csv") as rows:
        readings = {round(float(row["t_s"]) * 1e9 / period_ns): float(row["ctl.u[0]"]) for row in csv.DictReader(rows)}
    for cycle in lost:
        assert readings[cycle] == readings[cycle - 1], (cycle, readings)  # kept the last values
    assert all(value <= cycle for cycle, value in readings.items()), readings  # never an answer not yet asked for
    assert readings[max(readings)] > max(lost), readings  # and the drive's answers came again after them

    until_s = first_miss_s(tmp_path / "run")
    assert until_s is not None and until_s <= (min(stale) - 1) * period_ns / 1e9
    rtloop.simulate(app("can_stale_sim"), 20 * period_ns / 1e9, tmp_path / "sim")
    compared, differ_s = compare_signals(tmp_path / "run" / "signals.csv", tmp_path / "sim" / "signals.csv", until_s)
    assert differ_s is None and compared >= 1
    result = replay(tmp_path / "run", tmp_path / "replay", app("can_stale"))
    assert result.equal, result.divergence.describe() if result.divergence else result.cannot
    assert any(note.startswith(f"device 'drive' read stale values in {len(stale)} cycles") for note in result.notes)
