"""Bad device declarations: one line naming the file and key, exit 2, nothing started.

Frame declarations are checked when the app loads (anywhere); an interface that is not
there, a busy GPIO line or a device this user may not open need the guest's devices and
are checked there too (``tests/test_io_gpio.py``, ``test_io_can.py``, ``test_io_spi.py``)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

APP = """name = "{name}"
[tasks.ctl]
runnable = "rt_test_runnables:Gain"
period_ns = 10_000_000
[devices.drive]
kind = "can"
task = "ctl"
interface = "vcan0"
{settings}
"""

CASES = {
    "id_clash": ('send = [{ id = 0x200 }]\nreceive = [{ id = 0x200, timeout_ms = 5 }]',
                 "devices.drive.receive[0].id: frame id clash: 0x200 is also the id of send[0]"),
    "does_not_fit": ('send = [{ id = 0x200, signals = [{ name = "torque", start_byte = 6, type = "i32" }] }]',
                     "devices.drive.send[0].signals[0] ('torque'): a i32 at byte 6 ends at byte 10, past the "
                     "frame's 8 bytes: the layout does not fit the frame"),
    "fd_length": ('fd = true\nsend = [{ id = 0x200, length = 33 }]',
                  "devices.drive.send[0].length: a CAN FD frame carries one of"),
    "heartbeat_clash": ('heartbeat = { id = 0x200 }\nsend = [{ id = 0x200 }]',
                        "devices.drive.heartbeat.id: frame id clash"),
    "unknown_key": ('send = [{ id = 0x200, signals = [{ name = "a", start_byte = 0, sclae = 2.0 }] }]',
                    "devices.drive.send[0].signals[0]: unknown key 'sclae'"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_bad_frame_declaration_is_one_line_exit_2_nothing_started(case, tmp_path):
    settings, message = CASES[case]
    app = tmp_path / "app.toml"
    app.write_text(APP.format(name=f"bad_{case}_{os.getpid()}", settings=settings))
    out = tmp_path / "run"
    tests = Path(__file__).resolve().parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tests), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, "-m", "rtloop", "run", str(app), "--duration", "0.1", "--out", str(out)],
                         capture_output=True, text=True, timeout=60, env=env)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and str(app) in lines[0], run.stderr
    assert not out.exists()


TWO_DEVICES = APP + """[tasks.other]
runnable = "rt_test_runnables:Gain"
period_ns = 10_000_000
[devices.drive2]
kind = "can"
task = "other"
interface = "{interface2}"
{settings2}
"""


def _run_two_devices(tmp_path, settings: str, settings2: str, interface2: str = "vcan0") -> subprocess.CompletedProcess:
    app = tmp_path / "app.toml"
    app.write_text(TWO_DEVICES.format(name=f"two_writers_{os.getpid()}", settings=settings, settings2=settings2,
                                      interface2=interface2))
    tests = Path(__file__).resolve().parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tests), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "rtloop", "run", str(app), "--duration", "0.1",
                           "--out", str(tmp_path / "run")], capture_output=True, text=True, timeout=60, env=env)


@pytest.mark.parametrize(("settings2", "message"), [
    ("send = [{ id = 0x200 }]", "devices.drive2.send[0].id: frame id clash: 0x200 on vcan0 is also sent by "
                                "devices.drive.send[0]"),
    ("heartbeat = { id = 0x700 }", "devices.drive2.heartbeat.id: frame id clash: 0x700 on vcan0 is also sent by "
                                   "devices.drive.heartbeat"),
    ("send = [{ id = 0x700 }]", "devices.drive2.send[0].id: frame id clash: 0x700 on vcan0 is also sent by "
                                "devices.drive.heartbeat"),
    ("receive = [{ id = 0x200, timeout_ms = 2 }]", "devices.drive2.receive[0].id: frame id clash: 0x200 on vcan0 "
                                                   "is also sent by devices.drive.send[0]"),
    ("send = [{ id = 0x180 }]", "devices.drive2.send[0].id: frame id clash: 0x180 on vcan0 is also received by "
                                "devices.drive.receive[0]"),
])
def test_two_devices_sending_one_id_on_one_bus_are_refused_at_load(tmp_path, settings2, message):
    run = _run_two_devices(tmp_path, "heartbeat = { id = 0x700 }\nsend = [{ id = 0x200 }]\n"
                                     "receive = [{ id = 0x180, timeout_ms = 2 }]", settings2)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and str(tmp_path / "app.toml") in lines[0], run.stderr
    assert not (tmp_path / "run").exists()


def test_one_id_sent_on_two_buses_or_received_twice_loads():
    from rt_test_runnables import Noop
    from rtloop.app.builder import App
    from rtloop.io.can import CanDevice
    from rtloop.io.device import build_device

    app = App(f"can_apart_{os.getpid()}")
    for task in ("a", "b", "c"):
        app.add_task(task, Noop(), period_ns=10_000_000)
    frames = {"send": [{"id": 0x200}], "receive": [{"id": 0x180, "timeout_ms": 2}]}
    app.add_device("on_can0", build_device(CanDevice, "on_can0", {"interface": "can0", **frames}, ""), task="a")
    app.add_device("on_can1", build_device(CanDevice, "on_can1", {"interface": "can1", **frames}, ""), task="b")
    listener = build_device(CanDevice, "listener", {"interface": "can0", "receive": frames["receive"]}, "")
    app.add_device("listener", listener, task="c")  # receives 0x180 as on_can0 does: allowed
    assert sorted(app.devices) == ["listener", "on_can0", "on_can1"]
