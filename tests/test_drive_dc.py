"""Distributed clocks of the EtherCAT drive device against the emulated drives (veth, root; skipped
otherwise): SYNC0 starts at the release rtloop meant, cycling with the period, as the emulator's
own log says; a slave without DC runs free on the frames and the run says which way each ran; a
reference clock whose time stops coming back is a named fault. Without a bus: the ``dc`` key."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from conftest import unique_name
from drive_veth import example_app, start_emulator, stop, veth_pair
from rtloop.errors import DeviceError
from rtloop.io.device import build_device
from rtloop.io.drives.emulator import DEFAULT_IDENTITY
from rtloop.io.drives.ethercat_dc import dc_plan, first_release
from rtloop.io.drives.joints import joint_from_table
from rtloop.io.drives.pdo import DEFAULT_RXPDO, DEFAULT_TXPDO

PERIOD_MS = 10  # a frame must come back within the period: on a loaded 2-core host a Python emulator can take ms
TILT = "gear_ratio = 76.0\n"  # the tilt joint's line (the second joint): a key added after it is the tilt's
STARVED = "did not come back within"
ACTIVATED = re.compile(r"slave (\d): DC SYNC0 activated: start at system time (\d+) ns \(CLOCK_MONOTONIC (\d+) ns "
                       r"here\), cycle (\d+) ns")


@pytest.fixture
def veth() -> Iterator[tuple[str, str]]:
    yield from veth_pair()


def _esi(folder: Path, dc: bool) -> Path:
    """An ESI file of the emulated drive, with or without a DC operation mode."""
    entries = "".join(f"<Entry><Index>#x{index:04X}</Index></Entry>" for index in DEFAULT_RXPDO)
    tx_entries = "".join(f"<Entry><Index>#x{index:04X}</Index></Entry>" for index in DEFAULT_TXPDO)
    mode = "<Dc><OpMode><Name>DC</Name><AssignActivate>#x0300</AssignActivate></OpMode></Dc>" if dc else ""
    path = folder / f"drive_{'dc' if dc else 'free'}.xml"
    path.write_text(f"<EtherCATInfo><Vendor><Id>#x{DEFAULT_IDENTITY.vendor:X}</Id></Vendor><Descriptions><Devices>"
                    f"<Device><Type ProductCode=\"#x{DEFAULT_IDENTITY.product:X}\" "
                    f"RevisionNo=\"#x{DEFAULT_IDENTITY.revision:X}\">drive</Type><RxPdo>{entries}</RxPdo>"
                    f"<TxPdo>{tx_entries}</TxPdo>{mode}</Device></Devices></Descriptions></EtherCATInfo>")
    return path


def _run(app: Path, tmp_path: Path, *inject: str) -> tuple[subprocess.CompletedProcess[str], str, Path]:
    """The app against fresh emulated drives for 1.5 s (or until a fault); the emulator's log. A run
    that a host too loaded to let the emulator answer in time ended is tried again (three times)."""
    for attempt in range(3):
        log, out = tmp_path / f"drives{attempt}.log", tmp_path / f"run{attempt}"
        emulator = start_emulator(app, log, *(("--inject", inject[0]) if inject else ()))
        try:
            run = subprocess.run([sys.executable, "-m", "rtloop", "run", str(app), "--duration", "1.5", "--out",
                                  str(out)], capture_output=True, text=True, timeout=120)
        finally:
            stop(emulator)
        text = log.read_text()
        if STARVED not in run.stderr or (inject and "injected" in text):
            return run, text, out
    pytest.fail(f"every run's frame came back late (the host starved the emulator): {run.stderr}")


def _notes(out: Path) -> list[str]:
    notes: list[str] = json.loads((out / "summary.json").read_text())["notes"]
    return notes


def _release_ns(out: Path, cycle: int) -> int:
    for line in (out / "timing.csv").read_text().splitlines()[1:]:
        fields = line.split(",")
        if int(fields[1]) == cycle:
            return int(fields[2])
    raise AssertionError(f"no cycle {cycle} in timing.csv")


@pytest.mark.slow
@pytest.mark.parametrize("shift_us", [0, 1500])
def test_sync0_starts_at_the_release_rtloop_meant_and_cycles_with_the_period(veth: tuple[str, str], tmp_path: Path,
                                                                             shift_us: int) -> None:
    shift = {"watchdog_ms = 100": f"watchdog_ms = 100\nsync0_shift_us = {shift_us}"} if shift_us else {}
    app = example_app(tmp_path, *veth, unique_name("ecat_dc"), PERIOD_MS, **shift)
    run, text, out = _run(app, tmp_path)
    assert run.returncode == 0, run.stderr + text
    activated = {int(m[1]): (int(m[2]), int(m[3]), int(m[4])) for m in ACTIVATED.finditer(text)}
    assert sorted(activated) == [1, 2], text
    notes = [note for note in _notes(out) if "distributed clocks" in note]
    assert len(notes) == 2 and "(the reference clock)" in notes[0], notes
    found = re.search(r"from release (\d+) \(T0 \+ \d+·P[^=]* = system time (\d+) ns; .* ± (\d+) ns", notes[0])
    assert found, notes
    k, start_ns, uncertainty_ns = int(found[1]), int(found[2]), int(found[3])
    release_ns = _release_ns(out, k)
    for slave, (system_ns, monotonic_ns, cycle_ns) in activated.items():
        assert cycle_ns == PERIOD_MS * 1_000_000  # SYNC0's cycle time: the period
        assert system_ns == start_ns  # one start time for every slave, in the DC system time
        # and in the emulator's own clock (CLOCK_MONOTONIC, the run's): the release, within the
        # mapping's uncertainty (half the reference's read) and the frame's way down the line
        assert abs(monotonic_ns - (release_ns + shift_us * 1000)) <= uncertainty_ns + 250 * slave, \
            (slave, monotonic_ns, release_ns)
        assert f"slave {slave}: DC SYNC0 first pulse at system time {start_ns} ns" in text
    assert "runs on distributed clocks" in run.stdout + run.stderr  # the console says it too
    # how far SYNC0 slid against the releases by the end: the emulator's clocks do not drift, so
    # nothing beyond the two readings' uncertainty (a real reference clock's crystal would show here)
    slide = re.search(r"SYNC0 slid ([-+][\d.]+) µs ± ([\d.]+) µs against rtloop's releases over ([\d.]+) s",
                      " ".join(_notes(out)))
    assert slide, _notes(out)
    assert abs(float(slide[1])) <= float(slide[2]) + 0.25 * 2 + 0.1, slide[0]
    assert float(slide[3]) >= 1.0


@pytest.mark.slow
def test_a_slave_without_dc_runs_free_and_the_run_says_which_way_each_ran(veth: tuple[str, str],
                                                                        tmp_path: Path) -> None:
    esi = _esi(tmp_path, dc=False)
    app = example_app(tmp_path, *veth, unique_name("ecat_free"), PERIOD_MS, **{TILT: TILT + f'esi = "{esi}"\n'})
    run, text, out = _run(app, tmp_path)
    assert run.returncode == 0, run.stderr + text
    assert "2: vendor 0x00000A7E, product 0x00402402, revision 0x00010000, no distributed clocks" in text
    assert "slave 1: DC SYNC0 activated" in text and "slave 2: DC SYNC0" not in text
    assert "slave 2: drive: operation enabled (csp)" in text  # driven all the same, on the frames
    notes = " ".join(_notes(out))
    assert "joint 'pan' (slave 1) runs on distributed clocks" in notes
    assert "joint 'tilt' (slave 2) runs free on the frames, without distributed clocks: the slave has no DC unit " \
           "(ESC feature register 0x0008)" in notes


@pytest.mark.slow
def test_io_list_says_which_slaves_have_distributed_clocks(veth: tuple[str, str], tmp_path: Path) -> None:
    esi = _esi(tmp_path, dc=False)
    app = example_app(tmp_path, *veth, unique_name("ecat_dcls"), PERIOD_MS, **{TILT: TILT + f'esi = "{esi}"\n'})
    emulator = start_emulator(app, tmp_path / "drives.log")
    try:
        listing = subprocess.run([sys.executable, "-m", "rtloop", "io", "list", "--ethercat", veth[0]],
                                 capture_output=True, text=True, timeout=120)
    finally:
        stop(emulator)
    assert listing.returncode == 0, listing.stderr
    lines = {line.split(" slave ")[1][:1]: line for line in listing.stdout.splitlines() if " slave " in line}
    assert "distributed clocks (AssignActivate 0x0300)" in lines["1"], listing.stdout
    assert "no distributed clocks" in lines["2"], listing.stdout


@pytest.mark.slow
@pytest.mark.parametrize("pure", [False, True], ids=["c_cycle", "python_reference"])
def test_a_reference_clock_whose_time_stops_coming_back_is_a_named_fault(veth: tuple[str, str], tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch,
                                                                         pure: bool) -> None:
    monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1" if pure else "0")  # the C cycle's check, and the reference's
    app = example_app(tmp_path, *veth, unique_name("ecat_ref"), PERIOD_MS)
    run, text, _ = _run(app, tmp_path, "clock:1@20")
    assert run.returncode == 1, run.stderr
    assert "the reference clock's time did not come back" in run.stderr and "slave 1's system time" in run.stderr
    assert "Traceback" not in run.stderr
    assert "slave 2: drive: quick stop (controlword)" in text.split("injected loss")[1]


def _device(**joint: object) -> object:
    table = {"name": "pan", "vendor": DEFAULT_IDENTITY.vendor, "product": DEFAULT_IDENTITY.product,
             "revision": DEFAULT_IDENTITY.revision, "counts_per_rev": 4096, **joint}
    return build_device("ethercat", "arm", {"interface": "ecm0", "joints": [table]}, "app.toml")


def test_the_dc_key_is_true_or_false_and_true_needs_a_dc_mode_in_the_esi(tmp_path: Path) -> None:
    with pytest.raises(DeviceError, match=r"devices\.arm\.joints\[0\]\.dc: expected true .* got 'yes'"):
        _device(dc="yes")
    with pytest.raises(DeviceError, match=r"joints\[0\]\.dc: the joint's ESI file describes no distributed clocks"):
        _device(dc=True, esi=str(_esi(tmp_path, dc=False)))
    assert _device(esi=str(_esi(tmp_path, dc=True))).joints[0].esi_dc is True
    with pytest.raises(DeviceError, match=r"joints\[0\]\.dc: distributed clocks are EtherCAT's"):
        build_device("canopen402", "axis", {"interface": "vcan0", "joints": [
            {"name": "w", "node": 3, "counts_per_rev": 4096, "vendor": 1, "product": 1, "revision": 1,
             "dc": True}]}, "t")


def test_sync0_starts_on_the_first_release_far_enough_ahead() -> None:
    assert first_release(t0_ns=1_000_000_000, period_ns=1_000_000, now_ns=900_000_000, lead_ns=20_000_000) == 0
    assert first_release(t0_ns=1_000_000_000, period_ns=1_000_000, now_ns=990_000_000, lead_ns=20_000_000) == 10
    assert first_release(t0_ns=1_000_000_000, period_ns=3_000_000, now_ns=990_000_001, lead_ns=20_000_000) == 4


def test_each_joint_runs_on_dc_only_where_its_slave_and_its_esi_have_it_and_the_app_does_not_say_no(
        tmp_path: Path) -> None:
    def joint(slave: int, **extra: object):  # type: ignore[no-untyped-def]
        return joint_from_table({"name": f"j{slave}", "counts_per_rev": 4096, "vendor": 1, "product": 1,
                                 "revision": 1, **extra}, slave)

    free_esi = str(_esi(tmp_path, dc=False))
    joints = (joint(1), joint(2, dc=False), joint(3), joint(4, esi=free_esi, vendor=1), joint(5), joint(6, dc=True))
    plan, problem = dc_plan(joints, [0, 0x0300, 0, 0x0300, 0x0300, 0x0300], [False, True, True, True, True, True])
    assert problem == ""
    assert plan.reference == 2  # the first slave with a DC unit, whether rtloop starts its SYNC0 or not
    assert plan.with_dc == 5  # the FRMW's working counter: every slave with a DC unit
    assert plan.synced == {5: 0x0300, 6: 0x0300}
    assert plan.free == {1: "the slave has no DC unit (ESC feature register 0x0008)",
                         2: "dc = false in the app file",
                         3: "the slave describes no DC mode in its SII (category 60)",
                         4: "its ESI file describes no DC mode"}
    _, problem = dc_plan((joint(1, dc=True),), [0], [True])
    assert problem == "joints[0].dc: slave 1 describes no DC mode in its SII (category 60): it cannot run on them"
