"""The CANopen axis example in the PREEMPT_RT test guest, on vcan0, against the emulated drive node
in its own process: ``rtloop io list --canopen`` finds the node, the run reaches operation enabled,
turns the wheel, equals ``rtloop simulate`` bit for bit, and ends with the node in quick stop, then
disabled, as the node's own log says.

Kept short for CI's guest tier (one run of 40 cycles at 10 Hz under emulation, the simulation
beside the node's start): in the guest the exchange (the node's answer, at SCHED_FIFO) and the
task's step take milliseconds, and a busy host stalls the whole guest for 100 ms and more, so its
cycles miss their deadlines whatever rtloop does (no timing in the guest means anything:
docs/rtkernel-guest.md). The task therefore runs with ``overrun = "catch_up"``: a late cycle is
run late, never skipped, and since the drive steps once per SYNC and the profile follows the
cycle's k·P, the whole run equals its simulation, not only up to the first miss; the waits that
would fault (TPDOs, heartbeats) are stretched to 2 s. On the host, where cycles keep their
deadlines, the same device and node meet over a socket pair: ``tests/test_drive_canopen.py``.
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


def _app(tmp_path: Path, interface: str, period_ns: int) -> Path:
    text = (EXAMPLE / "canopen_axis.toml").read_text()
    slow = period_ns >= 50_000_000
    for old, new in (('name = "canopen_axis"', f'name = "canopen_axis_{os.getpid()}"'),
                     ('interface = "vcan0"', f'interface = "{interface}"'),
                     ("period_ns = 10_000_000", f'period_ns = {period_ns}\noverrun = "catch_up"'),
                     ("tpdo_timeout_ms = 5 ", f"tpdo_timeout_ms = {2000 if slow else 5} "),
                     ("heartbeat_ms = 100 ", f"heartbeat_ms = {2000 if slow else 100} ")):
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    app = tmp_path / "canopen_axis.toml"
    app.write_text(text)
    (tmp_path / "axis_profile.py").write_text((EXAMPLE / "axis_profile.py").read_text())
    return app


def _start_node(app: Path, log: Path, *more: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "rtloop", "io", "emulate", "canopen", "--app", str(app),
                             "--log", str(log), "--sync-timeout-ms", str(scaled_s(0.1) * 1000 * 5),
                             "--priority", str(NODE_PRIORITY), *more], stderr=subprocess.PIPE, text=True)


def _wait_for_node(node: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + scaled_s(10)
    while "emulated CiA 402 drive" not in (log.read_text() if log.exists() else ""):
        if node.poll() is not None or time.monotonic() > deadline:
            node.kill()
            pytest.fail(f"the emulated node did not start: {node.communicate()[1]}")
        time.sleep(0.05)


def _late_cycles(out: Path, period_ns: int) -> list[str]:
    """The first cycles that ended after their deadline: cycle (start, end after the release, ms)."""
    from rtloop.runtime.replay.logs import read_timing

    records, _t0_ns = read_timing(out, {"controller": period_ns})
    return [f"{r.cycle} ({(r.start_ns - r.release_ns) / 1e6:.0f}, {(r.end_ns - r.release_ns) / 1e6:.0f})"
            for r in records["controller"] if r.end_ns > r.release_ns + period_ns][:5]


@pytest.mark.rtkernel
@pytest.mark.timeout(scaled_s(60))  # the node, a simulation, one run of 4 s (under emulation)
def test_the_canopen_axis_enables_equals_its_simulation_and_ends_in_quick_stop_then_disabled(tmp_path: Path) -> None:
    entry = guest_device("vcan")
    from replay_helpers import compare_signals, first_miss_s
    from rtloop.cli.main import main as cli_main
    from rtloop.io.drives.canopen_scan import canopen_nodes

    period_ns = 100_000_000 if slowdown() > 1 else 10_000_000
    duration_s = CYCLES * period_ns / 1e9
    app = _app(tmp_path, entry["interface"], period_ns)
    out, log = tmp_path / "run", tmp_path / "node.log"
    started_s = time.monotonic()
    node = _start_node(app, log)  # fresh: the twin's drive starts at rest too
    try:
        # in this process, beside the node's start: a Python process more costs tens of seconds here
        assert cli_main(["simulate", str(app), "--duration", str(duration_s), "--out", str(tmp_path / "sim"),
                         "-q"]) == 0
        _wait_for_node(node, log)
        listed = [(item.path, item.detail) for item in canopen_nodes(entry["interface"], wait_s=2.0)]
        assert [path for path, _detail in listed] == [f"{entry['interface']} node 3"], listed  # io list --canopen
        assert listed[0][1].startswith("CANopen node: vendor 0x00000A7E, product 0x00402402, revision 0x00010000, ")
        listed_s = time.monotonic()
        run = subprocess.run([sys.executable, "-m", "rtloop", "run", str(app), "--duration", str(duration_s),
                              "--out", str(out), "-q"], capture_output=True, text=True, timeout=scaled_s(60))
        ran_s = time.monotonic()
    finally:
        node.send_signal(signal.SIGTERM)
        node.communicate(timeout=scaled_s(10))
    said = log.read_text()
    assert run.returncode == 0, f"{run.stderr}\nnode log:\n{said}"
    enabled = said.index("drive operation enabled (csv)")
    quick_stop = said.index("drive quick stop (controlword)", enabled)
    assert said.index("drive switch on disabled (disable voltage)", quick_stop)  # after the quick stop
    assert "NMT pre-operational (NMT enter pre-operational)" in said[quick_stop:]
    compared, differ_s = compare_signals(out / "signals.csv", tmp_path / "sim" / "signals.csv", None)
    late = f"first miss at {first_miss_s(out)} s, late cycles {_late_cycles(out, period_ns)}"
    print(f"{compared} rows equal; {late}; the node, simulation and list took {listed_s - started_s:.0f} s, "
          f"the run {ran_s - listed_s:.0f} s")
    assert differ_s is None, f"the run left its simulation at {differ_s} s ({late})"
    rows = [len((folder / "signals.csv").read_text().splitlines()) - 1 for folder in (out, tmp_path / "sim")]
    assert compared == rows[0] == rows[1] >= CYCLES - 1, f"{compared} rows equal; rows run, sim: {rows}"


def _wait_in_log(log: Path, text: str, timeout_s: float) -> str:
    deadline = time.monotonic() + timeout_s
    while text not in (said := log.read_text()):
        if time.monotonic() > deadline:
            pytest.fail(f"the node's log never said {text!r}:\n{said}")
        time.sleep(0.05)
    return said


@pytest.mark.rtkernel
@pytest.mark.timeout(scaled_s(60))  # the node and one run (under emulation: a few minutes)
@pytest.mark.parametrize("way", ["ctrl-c", "drive fault", "sigkill"])
def test_every_way_out_leaves_the_drive_quick_stopped_then_disabled(tmp_path: Path, way: str) -> None:
    """Ctrl-C (the task's safe transition), a drive fault (EMCY: a named fault, the run fails) and
    SIGKILL of the task process (nothing of the task's runs: the supervisor's NMT stop, the node's
    SYNC and heartbeat watch): each ends with the drive stopped, as the node's own log says. Each
    costs the guest a run: by hand only (tools/rtkernel/ci-guest-tier.sh)."""
    from conftest import wait_for_app, wait_for_task_pids

    entry = guest_device("vcan")
    period_ns = 100_000_000 if slowdown() > 1 else 10_000_000
    app = _app(tmp_path, entry["interface"], period_ns)
    log = tmp_path / "node.log"
    node = _start_node(app, log, *(["--inject", "fault@3"] if way == "drive fault" else []))
    process = None
    try:
        _wait_for_node(node, log)
        process = subprocess.Popen([sys.executable, "-m", "rtloop", "run", str(app), "--duration", "3600", "--out",
                                    str(tmp_path / "run"), "-q"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                   text=True)
        if way == "drive fault":
            _, stderr = process.communicate(timeout=scaled_s(30))
            assert process.returncode == 1, stderr
            line = next(text for text in stderr.splitlines() if text.startswith("rtloop run: task"))
            assert "joint 'wheel' (node 3)" in line and "0x5530" in line and "Traceback" not in stderr, stderr
            said = _wait_in_log(log, "NMT pre-operational (NMT enter pre-operational)", scaled_s(5))
            assert "injected drive fault at SYNC 3" in said and "EMCY 0x5530" in said
            return
        running = wait_for_app(f"canopen_axis_{os.getpid()}", process, timeout_s=scaled_s(30))
        _wait_in_log(log, "drive operation enabled (csv)", scaled_s(30))
        if way == "ctrl-c":
            process.send_signal(signal.SIGINT)
            _, stderr = process.communicate(timeout=scaled_s(30))
            assert process.returncode == 0, stderr  # an orderly stop by a signal
            said = _wait_in_log(log, "NMT pre-operational (NMT enter pre-operational)", scaled_s(5))
            enabled = said.index("drive operation enabled (csv)")
            quick = said.index("drive quick stop (controlword)", enabled)
            assert said.index("drive switch on disabled (disable voltage)", quick)
        else:
            os.kill(wait_for_task_pids(running, process)["controller"], signal.SIGKILL)
            said = _wait_in_log(log, "drive switch on disabled", scaled_s(30))
            process.communicate(timeout=scaled_s(30))
            after = said[said.index("drive operation enabled (csv)"):]
            assert "quick stop (controlword)" not in after  # nothing of the task's ran: the node stopped by itself
            assert "NMT stop: quick stop" in after or "(sync lost): quick stop" in after \
                or "heartbeat lost: quick stop" in after, said
    finally:
        if process is not None and process.poll() is None:
            process.kill()
        node.send_signal(signal.SIGTERM)
        node.communicate(timeout=scaled_s(10))
