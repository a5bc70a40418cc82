"""The CANopen axis example in the PREEMPT_RT test guest, on vcan0, against the emulated drive node
in its own process: it reaches operation enabled, equals ``rtloop simulate`` up to its first miss,
and ends with the node in quick stop, then disabled, as the node's own log says.

Kept short for the guest tier: 40 cycles at 10 Hz under emulation (the node's answer and the
task's step take milliseconds there; a busy host stalls the whole guest for 100 ms and more, so
the TPDOs may take 500 ms); run == simulate is a property of the schedule, not the rate.
On any machine the same device and node meet over a socket pair: ``tests/test_drive_canopen.py``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import guest_device, scaled_s, slowdown

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "canopen_axis"
CYCLES = 40
NODE_PRIORITY = 70  # the emulated drive answers at a real-time priority, below the controller's 80
MIN_COMPARED = 8  # the enabling (about 7 exchanges): in the guest the runs missed at the first enabled cycle
ATTEMPTS = 3


def _app(tmp_path: Path, interface: str, period_ns: int) -> Path:
    text = (EXAMPLE / "canopen_axis.toml").read_text()
    slow = period_ns >= 50_000_000
    for old, new in (('name = "canopen_axis"', f'name = "canopen_axis_{os.getpid()}"'),
                     ('interface = "vcan0"', f'interface = "{interface}"'),
                     ("period_ns = 10_000_000", f"period_ns = {period_ns}"),
                     ("tpdo_timeout_ms = 5 ", f"tpdo_timeout_ms = {500 if slow else 5} "),
                     ("heartbeat_ms = 100 ", f"heartbeat_ms = {1000 if slow else 100} ")):
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    app = tmp_path / "canopen_axis.toml"
    app.write_text(text)
    (tmp_path / "axis_profile.py").write_text((EXAMPLE / "axis_profile.py").read_text())
    return app


def _start_node(app: Path, log: Path) -> subprocess.Popen:
    node = subprocess.Popen([sys.executable, "-m", "rtloop", "io", "emulate", "canopen", "--app", str(app),
                             "--log", str(log), "--sync-timeout-ms", str(scaled_s(0.1) * 1000 * 5),
                             "--priority", str(NODE_PRIORITY)],
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + scaled_s(10)
    while "emulated CiA 402 drive" not in (log.read_text() if log.exists() else ""):
        if node.poll() is not None or time.monotonic() > deadline:
            node.kill()
            pytest.fail(f"the emulated node did not start: {node.communicate()[1]}")
        time.sleep(0.05)
    return node


def _late_cycles(out: Path, period_ns: int) -> list[str]:
    """The cycles that ended after their deadline: cycle (start, end after the release, ms)."""
    from rtloop.runtime.replay.logs import read_timing

    records, _t0_ns = read_timing(out, {"controller": period_ns})
    return [f"{r.cycle} ({(r.start_ns - r.release_ns) / 1e6:.0f}, {(r.end_ns - r.release_ns) / 1e6:.0f})"
            for r in records["controller"] if r.end_ns > r.release_ns + period_ns][:5]


@pytest.mark.rtkernel
@pytest.mark.timeout(scaled_s(200))  # a simulation and up to three runs of 4 s (under emulation)
def test_the_canopen_axis_enables_equals_its_simulation_and_ends_in_quick_stop_then_disabled(tmp_path: Path) -> None:
    entry = guest_device("vcan")
    from replay_helpers import compare_signals, first_miss_s

    period_ns = 100_000_000 if slowdown() > 1 else 10_000_000
    duration_s = CYCLES * period_ns / 1e9
    app = _app(tmp_path, entry["interface"], period_ns)
    sim = subprocess.run([sys.executable, "-m", "rtloop", "simulate", str(app), "--duration", str(duration_s),
                          "--out", str(tmp_path / "sim"), "-q"], capture_output=True, text=True, timeout=scaled_s(30))
    assert sim.returncode == 0, sim.stderr
    attempts: list[str] = []
    for attempt in range(ATTEMPTS):  # a busy host stalls the guest: a run whose first miss comes early is spoilt
        out, log = tmp_path / f"run{attempt}", tmp_path / f"node{attempt}.log"
        node = _start_node(app, log)  # fresh for each run: the twin's drive starts at rest too
        try:
            run = subprocess.run([sys.executable, "-m", "rtloop", "run", str(app), "--duration", str(duration_s),
                                  "--out", str(out), "-q"], capture_output=True, text=True, timeout=scaled_s(60))
        finally:
            node.send_signal(signal.SIGTERM)
            node.communicate(timeout=scaled_s(10))
        said = log.read_text()
        assert run.returncode == 0, f"{run.stderr}\nnode log:\n{said}"
        enabled = said.index("drive operation enabled (csv)")
        quick_stop = said.index("drive quick stop (controlword)", enabled)
        assert said.index("drive switch on disabled (disable voltage)", quick_stop)  # after the quick stop
        assert "NMT pre-operational (NMT enter pre-operational)" in said[quick_stop:]
        until_s = first_miss_s(out)
        compared, differ_s = compare_signals(out / "signals.csv", tmp_path / "sim" / "signals.csv", until_s)
        assert differ_s is None, f"the run left its simulation at {differ_s} s (first miss at {until_s} s)"
        attempts.append(f"run {attempt}: first miss at {until_s} s, {compared} rows equal; "
                        f"late cycles {_late_cycles(out, period_ns)}")
        print(attempts[-1])
        if compared >= MIN_COMPARED:
            break
    assert compared >= MIN_COMPARED, f"no run stayed on schedule for {MIN_COMPARED} cycles: {attempts}"
    # Weak on purpose, and said so: the guest runs here missed at the first enabled cycle (0.5-0.7 s,
    # three runs in four), so the compared window holds the enabling but not yet the wheel turning;
    # the wheel's following is compared bit for bit on the host (tests/test_drive_canopen.py).
