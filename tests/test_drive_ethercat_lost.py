"""Lost frames on the EtherCAT drive device (``lost_frames_max``): a cycle whose frame does not come
back within ``timeout_us`` keeps its readings, says so in ``frame_ok`` and is counted; the next
cycle goes on; a late answer is drained, never taken for a later cycle's; one more in a row than
the key allows is the fault it is without it; a value that would run the drives blind past their
SM watchdog is refused as the app loads. The veth tests need root (skipped otherwise)."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from conftest import unique_name
from drive_veth import example_app, start_emulator, stop, veth_pair
from rtloop import Runnable
from rtloop.app.builder import App
from rtloop.errors import DeviceError, DeviceFault

PERIOD_MS = 10  # the example's period in the drive tests: a loaded 2-core host answers within it
ATTEMPTS = 3
WATCHDOG = "watchdog_ms = 100"


class _Hold(Runnable):
    """A task with nothing to do (the device's own checks are under test)."""

    n_inputs = n_outputs = 0

    def step(self, u: object, y: object) -> None:
        pass


@pytest.fixture
def veth() -> Iterator[tuple[str, str]]:
    yield from veth_pair()


def _rtloop(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rtloop", *args], capture_output=True, text=True, timeout=180)


def _with_lost_frames_max(n: int) -> dict[str, str]:
    return {WATCHDOG: f"{WATCHDOG}\nlost_frames_max = {n}"}


@pytest.mark.parametrize(("period_ms", "lost_frames_max", "words"), [
    (2, 49, "49 lost frames in a row at the task's period of 2 ms leave the drives unwatched for 100 ms, not less "
            "than 100 ms (the slaves' SM watchdog, watchdog_ms = 100): at most 48"),
    (0.25, 300, "300 is too many: at most 254"),
])
def test_lost_frames_max_that_runs_the_drives_blind_too_long_is_refused_as_the_app_loads(
        tmp_path: Path, period_ms: float, lost_frames_max: int, words: str) -> None:
    app = example_app(tmp_path, "ecm9", "ecs9", "ecat_blind", period_ms, **_with_lost_frames_max(lost_frames_max))
    result = _rtloop("simulate", str(app), "--duration", "0.1", "--out", str(tmp_path / "sim"), "-q")
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert f"devices.gimbal.lost_frames_max: {words}" in result.stderr, result.stderr
    assert not (tmp_path / "sim").exists()


def test_the_bound_follows_the_watchdog_and_the_task_period_in_python_too() -> None:
    from rtloop.io.drives.emulator import DEFAULT_IDENTITY

    joint = {"name": "pan", "vendor": DEFAULT_IDENTITY.vendor, "product": DEFAULT_IDENTITY.product,
             "revision": DEFAULT_IDENTITY.revision, "mode": "csp", "counts_per_rev": 4096}
    app = App("ecat_blind_py")
    app.add_task("t", _Hold(), period_ns=1_000_000)
    app.add_device("fine", "ethercat", task="t", interface="ecm8", joints=[joint], watchdog_ms=20.0,
                   lost_frames_max=18)  # 19 ms blind: within the 20 ms watchdog
    assert "frame_ok" in app.devices["fine"].device.reading_names()
    with pytest.raises(DeviceError, match=r"lost_frames_max: 19 lost frames .* unwatched for 20 ms"):
        app.add_device("blind", "ethercat", task="t", interface="ecm7", joints=[joint], watchdog_ms=20.0,
                       lost_frames_max=19)


def test_a_timeout_past_the_period_counts_in_the_bound() -> None:
    """A lost frame's cycle waits timeout_us for its answer: past the period, the next frame goes out
    only at the release after it, so one lost frame already leaves the drives that long unwatched. A
    99 ms timeout at 1 ms with a 100 ms watchdog let a single tolerated lost frame trip the watchdog."""
    from rtloop.io.drives.emulator import DEFAULT_IDENTITY

    joint = {"name": "pan", "vendor": DEFAULT_IDENTITY.vendor, "product": DEFAULT_IDENTITY.product,
             "revision": DEFAULT_IDENTITY.revision, "mode": "csp", "counts_per_rev": 4096}
    app = App("ecat_slow_timeout")
    app.add_task("t", _Hold(), period_ns=1_000_000)
    app.add_device("below", "ethercat", task="t", interface="ecm5", joints=[joint], watchdog_ms=100.0,
                   timeout_us=900.0, lost_frames_max=98)  # 99 ms blind
    app.add_device("past", "ethercat", task="t", interface="ecm4", joints=[joint], watchdog_ms=100.0,
                   timeout_us=20_000.0, lost_frames_max=79)  # 79 + 20 periods: 99 ms
    with pytest.raises(DeviceError, match=r"lost_frames_max: 1 lost frames in a row at the task's period of 1 ms "
                                          r"\(timeout_us = 99000 µs is past the period: a lost frame's cycle takes 99 "
                                          r"periods\) leave the drives unwatched for 100 ms, .*: at most 0, or a "
                                          r"timeout_us below the period"):
        app.add_device("blind", "ethercat", task="t", interface="ecm3", joints=[joint], watchdog_ms=100.0,
                       timeout_us=99_000.0, lost_frames_max=1)
    with pytest.raises(DeviceError, match=r"lost_frames_max: 80 lost frames .* unwatched for 100 ms, .*: at most 79$"):
        app.add_device("blind", "ethercat", task="t", interface="ecm3", joints=[joint], watchdog_ms=100.0,
                       timeout_us=20_000.0, lost_frames_max=80)


def _rows(path: Path) -> list[list[str]]:
    with open(path, newline="") as file:
        return list(csv.reader(file))


def _first_miss_cycle(run: Path) -> int | None:
    """The planner's first cycle that ended past its deadline or followed a skip (lost frames aside)."""
    from rtloop.runtime.replay.logs import read_timing

    period_ns = PERIOD_MS * 1_000_000
    records, _ = read_timing(run, {"planner": period_ns}, [])
    previous = -1
    for record in records["planner"]:
        if record.cycle != previous + 1 or record.end_ns > record.release_ns + period_ns:
            return record.cycle
        previous = record.cycle
    return None


def _run_with(app: Path, tmp_path: Path, inject: str, lost: int) -> tuple[subprocess.CompletedProcess[str], Path, str]:
    """A 3 s run against fresh emulated drives with ``inject``; tried again (up to three times) where the
    loaded host lost frames of its own (not ``lost`` of them), missed a deadline before the injection, or
    stalled so long among the lost frames that releases were skipped between them (the fault then counts
    periods, not frames: seen once beside two suites and the QEMU guest)."""
    tried = []
    for attempt in range(ATTEMPTS):
        log, out = tmp_path / f"drives{attempt}.log", tmp_path / f"run{attempt}"
        emulator = start_emulator(app, log, "--inject", inject)
        try:
            run = _rtloop("run", str(app), "--duration", "3", "--out", str(out), "-q")
        finally:
            stop(emulator)
        text = log.read_text()
        summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else {}
        device = (summary.get("devices") or {}).get("gimbal") or {}
        first = (device.get("first_stale_cycles") or [0])[0]
        miss = _first_miss_cycle(out) if run.returncode == 0 else None
        skipped = "releases skipped between them" in run.stderr  # the host stalled among the lost frames
        held = device.get("stale_reads") == lost and (miss is None or miss > first + lost + 1)
        if "injected" in text and ((run.returncode != 0 and not skipped) or held):
            return run, out, text
        tried.append(f"exit {run.returncode}, {device.get('stale_reads')} lost, first miss {miss}: "
                     f"{run.stderr.strip()[-200:]}")
    pytest.fail(f"the host lost frames or missed deadlines of its own in every run: {tried}")


@pytest.mark.slow
@pytest.mark.parametrize(("inject", "lost"), [("lose:2@150", 2), ("late:12000@150", 1)])
def test_lost_or_late_frames_within_the_bound_hold_the_readings_and_the_run_goes_on(
        veth: tuple[str, str], tmp_path: Path, inject: str, lost: int) -> None:
    """The emulated slaves took the lost frames' outputs (lost on the way back) and the late one's: the
    drives moved as in the simulation, so every recorded row equals the simulation's but those that
    read the held positions (the planner's inputs at the lost cycles, its errors a period later). A late
    answer taken for the next cycle's would make that cycle's readings one cycle old: a row more differs."""
    app = example_app(tmp_path, *veth, unique_name("ecat_lost"), PERIOD_MS, **_with_lost_frames_max(2))
    sim = _rtloop("simulate", str(app), "--duration", "3", "--out", str(tmp_path / "sim"), "-q")
    assert sim.returncode == 0, sim.stderr
    run, out, text = _run_with(app, tmp_path, inject, lost)
    assert run.returncode == 0, f"{run.stderr}\n{text}"
    summary = json.loads((out / "summary.json").read_text())
    device = summary["devices"]["gimbal"]
    first = device["first_stale_cycles"][0]
    assert device["first_stale_cycles"] == list(range(first, first + lost)), device
    assert device["stale_reads_by_source"] == {"LRW frames not back within timeout_us": lost}, device
    assert any(f"{lost} cycle{'' if lost == 1 else 's'} whose LRW frame did not come back" in note and
               f"at most {lost} in a row (lost_frames_max = 2)" in note for note in summary["notes"]), summary["notes"]
    run_rows, sim_rows = _rows(out / "signals.csv"), _rows(tmp_path / "sim" / "signals.csv")
    assert run_rows[0] == sim_rows[0]
    miss = _first_miss_cycle(out)
    until = len(run_rows) - 1 if miss is None else miss  # a later miss of the loaded host: compared up to it
    differ = [k for k in range(until) if run_rows[k + 1] != sim_rows[k + 1]]
    assert differ and set(differ) <= set(range(first, first + lost + 1)), (first, differ)
    measured = run_rows[0].index("planner.pan_measured_rad")
    for k in range(first, first + lost):  # held: the position of the last frame that came
        assert run_rows[k + 1][measured] == run_rows[first][measured] != sim_rows[k + 1][measured]
    assert f"injected {'late answer' if inject.startswith('late') else 'lost frame'}" in text
    replayed = _rtloop("replay", str(out), "--out", str(tmp_path / "replay"))
    assert replayed.returncode == 0, replayed.stderr
    assert _rows(tmp_path / "replay" / "signals.csv") == run_rows  # the lost frames played back as the run read them


@pytest.mark.slow
def test_one_lost_frame_more_in_a_row_than_the_bound_is_the_fault_and_the_drives_quick_stop(
        veth: tuple[str, str], tmp_path: Path) -> None:
    app = example_app(tmp_path, *veth, unique_name("ecat_lost3"), PERIOD_MS, **_with_lost_frames_max(2))
    run, _out, text = _run_with(app, tmp_path, "lose:3@150", 3)
    assert run.returncode == 1, run.stderr
    line = next(text for text in run.stderr.splitlines() if text.startswith("rtloop run: task"))
    assert "the LRW frame did not come back within 9000 µs (timeout_us), 3 cycles in a row (lost_frames_max = 2)" \
        in line, run.stderr
    assert "Traceback" not in run.stderr
    assert "slave 1: drive: quick stop (controlword)" in text.split("injected lost frame")[1]


def _device_losing(lost_frames_max: int, period_ns: int = 1_000_000) -> tuple[Any, np.ndarray]:
    """An EtherCAT device past T0 whose frames are lost (no bus: its loss path alone), and its readings."""
    from rtloop.io.device import build_device
    from rtloop.io.drives.cycle import DriveCycle
    from rtloop.io.drives.emulator import DEFAULT_IDENTITY

    joint = {"name": "pan", "vendor": DEFAULT_IDENTITY.vendor, "product": DEFAULT_IDENTITY.product,
             "revision": DEFAULT_IDENTITY.revision, "mode": "csp", "counts_per_rev": 4096}
    device = build_device("ethercat", "arm", {"interface": "ecm6", "joints": [joint],
                                              "lost_frames_max": lost_frames_max}, "<test>")
    device.cycle = DriveCycle("arm", device.joints)
    device.timeline(0, period_ns)
    return device, np.full(device.n_outputs, 7.0)


def _lose_at(device: Any, sent_s: float, y: np.ndarray) -> None:
    device._sent_at = sent_s  # when the lost frame went out
    device._frame_lost(y)


def test_lost_frames_hold_the_readings_mark_frame_ok_and_the_one_too_many_is_the_fault() -> None:
    device, y = _device_losing(3)
    assert device.reading_names()[-1] == "frame_ok" and device.may_read_stale()
    for k in range(3):  # three in a row, one period apart: within the bound
        _lose_at(device, 10.0 + k * 0.001, y)
    assert list(y[:-1]) == [7.0] * (len(y) - 1) and y[-1] == 0.0  # held, and marked
    assert device.stale_reads == 3 and device.stale_sources() == {
        "LRW frames not back within timeout_us": 3}
    with pytest.raises(DeviceFault, match=r"did not come back within 1000 µs \(timeout_us\), 4 cycles in a row "
                                          r"\(lost_frames_max = 3\)"):
        _lose_at(device, 10.003, y)


def test_lost_frames_with_releases_skipped_between_them_count_the_periods_they_span() -> None:
    """A host stall that skips releases between two lost frames keeps the drives without the master
    for the whole span: two lost frames five periods apart are six periods' worth, past 3."""
    device, y = _device_losing(3)
    _lose_at(device, 10.0, y)
    with pytest.raises(DeviceFault, match=r"2 cycles in a row over 6 periods \(releases skipped between them\) "
                                          r"\(lost_frames_max = 3\)"):
        _lose_at(device, 10.005, y)


def test_the_emulator_injects_lost_frames_in_a_row_and_late_answers() -> None:
    from rtloop.io.drives.emulator import Injection, parse_injection

    assert parse_injection("lose@150") == Injection("lose", 1, 150)
    assert parse_injection("lose:3@150") == Injection("lose", 3, 150)
    assert parse_injection("late:12000@150") == Injection("late", 12000, 150)
    for bad in ("late@150", "lose:x@150", "late:1.5@150"):
        with pytest.raises(ValueError, match=r"expected fault:SLAVE@N, .* lose:K@N or late:US@N"):
            parse_injection(bad)


class _Drive:
    """The other end of a datagram socket pair in place of the bus: each LRW frame is taken (its
    controlwords kept) and, when ``answer``, answered as one slave in OP whose drive obeys the safe
    transition at once (quick stop: at rest in quick stop active; disable voltage: switch on disabled)."""

    def __init__(self, device: Any, end: Any, answer: bool) -> None:
        import threading

        self.device, self.end, self.answer = device, end, answer
        self.controlwords: list[int] = []
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        from rtloop.io.drives import cia402

        joint = self.device.cycle.joints[0]
        control_at = joint.out_at + joint.config.rx.offsets[cia402.CONTROLWORD]
        status_at = joint.in_at + joint.config.tx.offsets[cia402.STATUSWORD]
        while True:
            try:
                frame = bytearray(self.end.recv(2048))
            except OSError:
                return
            if not frame:
                return  # shut down by close()
            if frame[16] != 12:  # not the LRW (the state request)
                continue
            word = frame[control_at] | frame[control_at + 1] << 8
            self.controlwords.append(word)
            if self.answer:
                status = 0x0407 if word == cia402.CW_QUICK_STOP else 0x0040  # at rest in quick stop; disabled
                frame[status_at:status_at + 2] = status.to_bytes(2, "little")
                frame[self.device._wkc_at:self.device._wkc_at + 2] = (3).to_bytes(2, "little")
                try:
                    self.end.send(bytes(frame))
                except OSError:
                    return  # the device's end is closed: the test is over

    def close(self) -> None:
        """The device's end, then this thread and its end: none is left for another test's garbage
        collection (a ResourceWarning there, or this thread's late send failing in another test, was
        that test's failure)."""
        import contextlib
        import socket

        self.device.socket.close()
        with contextlib.suppress(OSError):
            self.end.shutdown(socket.SHUT_RDWR)
        self.thread.join(5)
        self.end.close()


def _device_stopping(lost_frames_max: int, answer: bool, quick_stop_timeout_s: float = 0.1) -> tuple[Any, _Drive]:
    """An EtherCAT device past T0 with its drive in operation enabled, on a socket pair (no bus)."""
    import socket
    import struct

    from rtloop.io.device import build_device
    from rtloop.io.drives.cycle import DriveCycle
    from rtloop.io.drives.emulator import DEFAULT_IDENTITY

    joint = {"name": "pan", "vendor": DEFAULT_IDENTITY.vendor, "product": DEFAULT_IDENTITY.product,
             "revision": DEFAULT_IDENTITY.revision, "mode": "csp", "counts_per_rev": 4096}
    device = build_device("ethercat", "arm", {"interface": "ecm2", "joints": [joint], "timeout_us": 2000.0,
                                              "quick_stop_timeout_s": quick_stop_timeout_s,
                                              "lost_frames_max": lost_frames_max},
                          "<test>")
    master, slave = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    master.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, struct.pack("@ll", 0, 1000))  # as open_raw's
    device._expected_wkc = 3
    device._bind(DriveCycle("arm", device.joints), master)
    device.cycle.joints[0].statusword = 0x0027  # operation enabled, as last read in the loop
    device.active = True
    return device, _Drive(device, slave, answer)


@pytest.mark.parametrize("lost_frames_max", [0, 2])
def test_a_safe_transition_whose_frames_are_lost_is_a_fault_that_says_so(lost_frames_max: int) -> None:
    """The cable pulled at the end: the safe transition sends its quick stop frame after frame, none
    comes back; after quick_stop_timeout_s it asks for SAFE-OP and says the drives are not known to be
    stopped (before, it returned as if they were: the run's summary said nothing)."""
    device, drive = _device_stopping(lost_frames_max, answer=False)
    try:
        with pytest.raises(DeviceFault, match=r"devices\.arm: the safe transition did not finish within 0\.1 s "
                                              r"\(quick_stop_timeout_s\): joint 'pan' in operation enabled "
                                              r"\(statusword 0x0027\); (\d+) of \1 frames not back within 2000 µs; "
                                              r"SAFE-OP asked for"):
            device.write_safe(np.zeros(device.n_inputs))
    finally:
        drive.close()
    assert drive.controlwords and set(drive.controlwords) == {0x0002}  # quick stop went out, frame after frame


def test_a_safe_transition_the_drive_follows_ends_quietly() -> None:
    """Quick stop until the drive is seen at rest, then disable voltage. The drive's thread answers
    each frame at once, but a loaded machine may run it after the frame's 1 ms receive timeout: that
    exchange is lost and the quick stop goes out again, so only the order is asserted (and the
    transition is given seconds: it ends as soon as the drive follows)."""
    device, drive = _device_stopping(2, answer=True, quick_stop_timeout_s=30.0)
    try:
        device.write_safe(np.zeros(device.n_inputs))
    finally:
        drive.close()
    assert 0x0000 in drive.controlwords, drive.controlwords  # disable voltage went out
    first_disable = drive.controlwords.index(0x0000)
    assert first_disable >= 1 and set(drive.controlwords[:first_disable]) == {0x0002}, drive.controlwords


def test_an_injection_that_cannot_happen_is_refused_not_made_on_another_slave() -> None:
    """``fault:3@N`` on two slaves hit slave 1 instead, and ``lose:0@N`` logged a loss it never made:
    a test would pass on the wrong evidence. Each is one line, exit 2."""
    from rtloop.io.drives.emulator import DEFAULT_IDENTITY, DriveSpec, parse_injection, serve
    from rtloop.io.drives.pdo import DEFAULT_RXPDO, DEFAULT_TXPDO

    for bad in ("lose:0@150", "late:0@150", "fault:0@150"):
        with pytest.raises(ValueError, match=r"must be at least 1"):
            parse_injection(bad)
    spec = DriveSpec(DEFAULT_IDENTITY, DEFAULT_RXPDO, DEFAULT_TXPDO)
    for bad in ("fault:3@100", "drop:3@100", "clock:5@100"):
        assert serve("ecm_none", [spec, spec], inject=(bad,)) == 2
    assert serve("ecm_none", [spec, spec], inject=("fault:2@100",)) == 3  # fine: on to the interface (none here)


def test_lost_frames_after_a_mode_change_do_not_count_as_the_drive_refusing_the_mode() -> None:
    """A mode change, then 60 lost frames (within lost_frames_max = 90 at 1 ms): the drive saw none of
    the frames asking for it, so the first frame back still shows the old mode. The lost cycles ran
    the wait for the mode (50 exchanges) on: a false 'it does not support it' fault."""
    from rtloop.io.device import build_device
    from rtloop.io.drives.cycle import DriveCycle
    from rtloop.io.drives.emulator import DEFAULT_IDENTITY

    joint = {"name": "pan", "vendor": DEFAULT_IDENTITY.vendor, "product": DEFAULT_IDENTITY.product,
             "revision": DEFAULT_IDENTITY.revision, "modes": ["csp", "csv"], "counts_per_rev": 4096}
    device = build_device("ethercat", "arm", {"interface": "ecm6", "joints": [joint], "lost_frames_max": 90},
                          "<test>")
    cycle = device.cycle = DriveCycle("arm", device.joints)
    device.timeline(0, 1_000_000)
    outputs, inputs = bytearray(cycle.output_bytes), bytearray(cycle.input_bytes)
    cycle.bind(outputs, 0, inputs, 0)
    cycle.enabled = True
    u, y = np.array([0.0, 0.0, 9.0]), np.zeros(device.n_outputs)  # csv asked for
    cycle.prepare_outputs(u)
    for k in range(60):
        _lose_at(device, 10.0 + k * 0.001, y)
    tx = cycle.joints[0].config.tx
    tx.struct.pack_into(inputs, 0, *[{0x6041: 0x0027, 0x6061: 8}.get(index, 0) for index in tx.objects])
    cycle.take_inputs(y)  # operation enabled, still in csp: the drive has not seen the request yet
    assert y[device.output_names.index("pan_mode")] == 8.0


def test_lost_frames_while_a_drive_resets_its_fault_do_not_use_up_the_resets() -> None:
    """A drive in fault at T0, then 30 lost frames (within lost_frames_max = 40): each lost cycle sent a
    fault reset or its falling edge again from the held statusword, and each reset counted as one the
    drive refused: a false 'stays in fault after 8 fault resets' at the 17th lost frame."""
    device, y = _device_losing(40)
    cycle = device.cycle
    cycle.bind(bytearray(cycle.output_bytes), 0, bytearray(cycle.input_bytes), 0)
    cycle.joints[0].statusword = 0x0008  # fault, as the last frame that came said
    for k in range(30):
        cycle.prepare_outputs(np.zeros(device.n_inputs))
        _lose_at(device, 10.0 + k * 0.001, y)
    assert cycle.joints[0].machine.reset_tries <= 1


def test_the_python_receive_waits_on_a_socket_numbered_past_1023() -> None:
    """The Python receive path (the C one's reference, and what runs without the C build) waits for a
    lost frame's timeout with ppoll: select() refuses a descriptor of 1024 or more ("filedescriptor out
    of range"), which a task holding many files, sockets and devices reaches."""
    import os
    import resource
    import socket

    device, _y = _device_losing(3)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < 1600:
        pytest.skip(f"this process may open no descriptor numbered 1500 (its hard limit is {hard})")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, 1600), hard))
    ours, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        high = socket.socket(fileno=os.dup2(ours.fileno(), 1500))
        device._expected_wkc = 3  # what configuring one slave sets (no bus here)
        device._bind(device.cycle, high)
        device._sent_at = time.monotonic()
        assert device._receive() == -1  # nothing came back within timeout_us: lost, no ValueError
        high.close()
    finally:
        ours.close()
        peer.close()
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def test_the_first_lost_frame_without_lost_frames_max_says_what_would_let_it_pass() -> None:
    from rtloop.io.drives.ethercat_lost import lost_frames_fault

    said = lost_frames_fault("exchange 6 on ecm0", 1, 800, 0)  # the emulated JIWY on a busy machine, by default
    assert said == ("exchange 6 on ecm0: the LRW frame did not come back within 800 µs (timeout_us): a slave lost, a "
                    "cable pulled, or the frame lost (a dropped frame, a stalled or busy host: lost_frames_max lets a "
                    "few in a row pass, docs/drives.md)")



def test_a_raw_socket_refused_says_run_as_root_not_setcap_on_python(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without CAP_NET_RAW (a user's run, `rtloop io list --ethercat`): the advice is to run rtloop as
    root; it once was `setcap cap_net_raw+ep` on the system's python3, which arms every Python program."""
    from rtloop.io.drives import ethercat, scan

    def refused(*_args: object, **_kwargs: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    for module in (scan, ethercat):
        monkeypatch.setattr(module, "interface_problem", lambda _name: "")
        monkeypatch.setattr(module, "open_raw", refused)
    [listed] = scan.ethercat_slaves("ecm7")
    assert listed.detail == "no permission for a raw socket" and not listed.usable
    assert "run rtloop as root" in listed.fix
    device, _y = _device_losing(3)
    with pytest.raises(DeviceError, match=r"ecm6: no permission for a raw socket: run rtloop as root") as error:
        device._master()
    for advice in (listed.fix, str(error.value)):
        assert "setcap cap_net_raw+ep" not in advice
