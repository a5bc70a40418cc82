"""A task process killed with SIGKILL, in the PREEMPT_RT test guest: nothing runs in it any more,
so the supervisor writes its devices' safe values from outside — the CAN frames with the safe
values (and no heartbeat after them), the GPIO output lines driven at their safe levels — and
summary.json says so.

The GPIO output is pulled up on the simulator's side: a line the kernel frees with the dead
process goes to its pull (gpio-sim; most SoC controllers keep the last level), so only the
supervisor's request can bring it to its safe 0. The supervisor holds the line until the run
ends; a second task whose postrun takes a while keeps that end a second or more away, so the
test's watch of the line (a Python thread reading it every millisecond, in an emulated guest
that its host stalls for tens of ms) sees the safe level for certain: without it, the run's end
came so soon after the kill that the watch once missed the held 0 altogether.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from io_guest_devices import SimLine, guest_device
from rtloop.ipc.ports import connect_app

COMMAND_ID, HEARTBEAT_ID = 0x2A1, 0x7A1

APP = """name = "{name}"
[tasks.ctl]
runnable = "rt_test_runnables:Gain"
args = {{ n = 3, gain = 0.0, offset = 1.0 }}
period_ns = 50_000_000
priority = 70

[devices.drive]
kind = "can"
task = "ctl"
interface = "{interface}"
heartbeat = {{ id = 0x7A1 }}
send = [{{ id = 0x2A1, signals = [{{ name = "torque", start_byte = 0, type = "f64" }}] }}]
limits.torque = {{ min = -5.0, max = 5.0, safe = -0.5 }}

[devices.panel]
kind = "gpio"
task = "ctl"
chip = "{chip}"
outputs = ["led"]

[tasks.linger]
runnable = "rt_test_runnables:SlowToStop"
args = {{ hold_s = 1.5 }}
period_ns = 50_000_000
priority = 60

[[connect]]
from = "ctl.y[0]"
to = "drive.u[0]"

[[connect]]
from = "ctl.y[1]"
to = "panel.u[0]"
"""


class CanListener(threading.Thread):
    """Every frame of the command and heartbeat ids seen on the bus: (id, first 8 data bytes)."""

    def __init__(self, interface: str) -> None:
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        filters = b"".join(struct.pack("=II", can_id, 0x7FF | 0x80000000) for can_id in (COMMAND_ID, HEARTBEAT_ID))
        self.sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, filters)
        self.sock.bind((interface,))
        self.sock.settimeout(0.2)
        self.frames: list[tuple[int, bytes]] = []
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.is_set():
            try:
                can_id, _length, data = struct.unpack("=IB3x8s", self.sock.recv(16))
            except TimeoutError:
                continue
            self.frames.append((can_id, data))
        self.sock.close()

    def commands(self) -> list[float]:
        return [struct.unpack("<d", data)[0] for can_id, data in self.frames if can_id == COMMAND_ID]


class LineWatch(threading.Thread):
    """The changes of a gpio-sim line's value, read every millisecond."""

    def __init__(self, line: SimLine) -> None:
        super().__init__(daemon=True)
        self.line = line
        self.values: list[int] = []
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.is_set():
            value = self.line.value
            if not self.values or value != self.values[-1]:
                self.values.append(value)
            time.sleep(0.001)


@pytest.mark.rtkernel
@pytest.mark.timeout(1200)
def test_kill_9_of_the_task_the_supervisor_sends_the_safe_frame_and_drives_the_safe_level(tmp_path):
    vcan, gpio = guest_device("vcan"), guest_device("gpio")
    pytest.importorskip("gpiod")
    led = SimLine(gpio, "led")
    led.pull(True)  # a freed line reads 1: only the supervisor's request can make it 0
    app = tmp_path / "app.toml"
    name = f"dead_task_{os.getpid()}"
    app.write_text(APP.format(name=name, interface=vcan["interface"], chip=gpio["device"]))
    tests = str(Path(__file__).resolve().parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")])}
    listener, watch = CanListener(vcan["interface"]), LineWatch(led)
    listener.start()
    watch.start()
    process = subprocess.Popen([sys.executable, "-m", "rtloop", "run", str(app), "--duration", "600", "--out",
                                str(tmp_path / "run"), "-q"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    try:
        deadline = time.monotonic() + 600  # start-up in an emulated guest
        while listener.commands().count(1.0) < 3 and time.monotonic() < deadline and process.poll() is None:
            time.sleep(0.05)
        assert listener.commands().count(1.0) >= 3, (listener.commands(), process.poll())
        assert watch.values[-1] == 1
        pid = connect_app(name, timeout_s=60).task_pids()["ctl"]
        assert pid, "no task process for ctl"
        killed_at, line_changes_before = len(listener.frames), len(watch.values)
        os.kill(pid, signal.SIGKILL)
        _, stderr = process.communicate(timeout=300)
    finally:
        if process.poll() is None:
            process.kill()
        time.sleep(0.3)
        listener.done.set()
        watch.done.set()
        listener.join()
        watch.join()
        led.pull(False)
    assert process.returncode != 0 and "killed by SIGKILL" in stderr, stderr
    after = listener.frames[killed_at:]
    safe = [i for i, (can_id, data) in enumerate(after)
            if can_id == COMMAND_ID and struct.unpack("<d", data)[0] == -0.5]
    assert safe, f"no safe frame after the kill: {after}"
    assert not any(can_id == HEARTBEAT_ID for can_id, _ in after[safe[0]:]), after  # the drive sees the loop gone
    notes = json.loads((tmp_path / "run" / "summary.json").read_text())["notes"]
    said = " | ".join(notes)
    assert "task ctl was killed by SIGKILL before its device 'drive' (can) got its safe values: the supervisor " \
           "sent its frames 0x2A1 with the safe values" in said, notes
    assert "before its device 'panel' (gpio) got its safe values: the supervisor holds its output lines at " \
           "their safe levels (led=0)" in said, notes
    assert 0 in watch.values[line_changes_before:], watch.values  # the supervisor drove the line to its safe 0
