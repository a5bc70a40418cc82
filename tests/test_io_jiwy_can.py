"""JIWY over CAN in the PREEMPT_RT test guest: the real-time run equals ``rtloop simulate`` with the twin.

The plant runs in ``examples/jiwy_can/plant_node.py``, a separate process on vcan0 speaking the
declared frames; the controller is a real-time task with a CAN device. Up to the run's first
deadline miss, its signals equal the simulation's bit for bit. When the run ends the heartbeat
stops and the node goes safe by itself."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import scaled_ns
from io_guest_devices import guest_device

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "jiwy_can"


@pytest.mark.timeout(1500)
def test_jiwy_over_can_equals_its_simulation_and_the_drive_goes_safe_when_the_heartbeat_stops(tmp_path):
    entry = guest_device("vcan")
    from rtloop.runtime.replay import compare_signals, first_miss_s

    app = tmp_path / "jiwy_can.toml"
    name = f"jiwy_can_{os.getpid()}"
    text = (EXAMPLE / "jiwy_can.toml").read_text().replace('name = "jiwy_can"', f'name = "{name}"')
    text = text.replace('interface = "vcan0"', f'interface = "{entry["interface"]}"')
    # the example's 10 ms stretched by the emulated guest's slowdown (the plant node is Python in it too)
    text = text.replace("period_ns = 10_000_000", f"period_ns = {max(scaled_ns(10_000_000), 10_000_000)}")
    text = text.replace('feed = "../jiwy/setpoints/step.csv"', f'feed = "{EXAMPLE.parent / "jiwy/setpoints/step.csv"}"')
    app.write_text(text)
    for module in ("jiwy_can_models.py",):
        (tmp_path / module).write_text((EXAMPLE / module).read_text().replace(
            'Path(__file__).resolve().parent.parent / "jiwy"', repr(str(EXAMPLE.parent / "jiwy"))))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    node = subprocess.Popen([sys.executable, str(EXAMPLE / "plant_node.py"), "--interface", entry["interface"],
                             "--heartbeat-timeout-ms", "300"], env=env, stderr=subprocess.PIPE, text=True)
    try:
        assert "waiting for steering frames" in node.stderr.readline()
        run = subprocess.run([sys.executable, "-m", "rtloop", "run", str(app), "--duration", "40", "--out",
                              str(tmp_path / "run"), "-q"], env=env, capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr
        time.sleep(1.0)  # the heartbeat stopped with the run: the node's watchdog trips after 300 ms
    finally:
        node.terminate()
        _, said = node.communicate(timeout=60)
    said_lines = said.strip().splitlines()
    assert "heartbeat seen: enabled" in said  # the drive enabled itself on the first heartbeat
    assert said_lines[-1] == "plant_node: heartbeat lost: steering zero (safe)", said  # and went safe at the end
    sim = subprocess.run([sys.executable, "-m", "rtloop", "simulate", str(app), "--duration", "40", "--out",
                          str(tmp_path / "sim"), "-q"], env=env, capture_output=True, text=True, timeout=600)
    assert sim.returncode == 0, sim.stderr
    until_s = first_miss_s(tmp_path / "run")
    compared, differ_s = compare_signals(tmp_path / "run" / "signals.csv", tmp_path / "sim" / "signals.csv", until_s)
    assert differ_s is None, f"the run left its simulation at {differ_s} s (first miss at {until_s} s)"
    if compared < 20:
        import json

        task = json.loads((tmp_path / "run" / "summary.json").read_text())["tasks"]["controller"]
        with open(tmp_path / "run" / "timing.csv") as timing:
            first_rows = [next(timing, "").strip() for _ in range(3)]
        pytest.skip(f"the run missed a deadline at {until_s} s, too early to show the equality ({compared} rows; "
                    f"cycles {task['cycles']}, misses {task['deadline_misses']}, overruns {task['overruns']}; "
                    f"timing.csv starts {first_rows})")


def test_the_drive_steps_its_plant_with_both_steering_values_as_the_twin_does():
    """Anywhere: the plant node's logic (no bus) answers each pair of steering frames with the angles
    the twin computes from the same two values (pan and tilt kept apart), bit for bit."""
    import struct

    import numpy as np

    sys.path[:0] = [str(EXAMPLE), str(EXAMPLE.parent / "jiwy")]
    try:
        from jiwy_can_models import Plant
        from plant_node import ANGLE_PAN, ANGLE_TILT, FRAME, HEARTBEAT, STEERING_PAN, STEERING_TILT, Drive
    finally:
        del sys.path[:2]
    drive, twin = Drive(0.01, 0.3), Plant(step_size_s=0.01)
    twin.prerun()
    angles = np.zeros(2)
    assert drive.on_frame(HEARTBEAT, bytes(8), 0.0) == []
    for cycle, (pan, tilt) in enumerate([(1.5, 0.6), (-0.25, 2.0), (3.0, -1.0), (0.0, 0.5)]):
        assert drive.on_frame(STEERING_PAN, struct.pack("<d", pan), 0.01 * cycle) == []
        answers = drive.on_frame(STEERING_TILT, struct.pack("<d", tilt), 0.01 * cycle)
        twin.step(np.array([pan, tilt]), angles)
        got = {FRAME.unpack(frame)[0]: struct.unpack_from("<d", FRAME.unpack(frame)[2])[0] for frame in answers}
        assert got == {ANGLE_PAN: angles[0], ANGLE_TILT: angles[1]}, cycle
    assert angles[0] != angles[1]
