"""The servo examples over a pty against the servo model (``rtloop emulate``): run == simulate, a silent
servo and a hardware error give the declared outcome, torque off at the model on every way a run ends,
and the bad input (an ID not on the bus, another model, two devices on one port, a range outside the
servo's limits or outside one turn, a bus not ready) as one line with its exit code."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

import rtloop
from conftest import unique_name, wait_for_the_task_pid
from replay_helpers import compare_signals, first_miss_s
from rtloop.app.appfile import load_app

pytest.importorskip("serial", reason="pyserial is not installed: pip install 'rtloop[servos]'")

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
JIWY = EXAMPLES / "jiwy_dynamixel" / "jiwy_dynamixel.toml"
SO100 = EXAMPLES / "so100_feetech" / "so100_feetech.toml"
ROOT = os.geteuid() == 0


class Emulator:
    """``rtloop emulate`` in its own process, its pty linked from ``folder/bus.tty``."""

    def __init__(self, folder: Path, *arguments: str) -> None:
        self.link = folder / "bus.tty"
        self.log = folder / "emulator.log"
        priority = ["--priority", "70"] if ROOT else []
        with open(self.log, "w") as log:
            self.process = subprocess.Popen([sys.executable, "-m", "rtloop", "emulate", "--link", str(self.link),
                                             *priority, *arguments], stdout=log, stderr=subprocess.STDOUT)
        self.since = 0
        """Lines before this one are an earlier run's (a model shared by several tests): not looked at."""
        try:
            self.wait_for("listening on")
        except BaseException:
            self.stop()  # (a model left running would outlive the tests)
            raise

    def lines(self) -> list[str]:
        return self.log.read_text().splitlines()[self.since:]

    def next_run(self) -> None:
        """What the model says from now on is the next run's."""
        self.since += len(self.lines())

    def wait_for(self, text: str, count: int = 1, timeout_s: float = 30.0) -> list[str]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            found = [line for line in self.lines() if text in line]
            if len(found) >= count:
                return found
            assert self.process.poll() is None, self.lines()
            time.sleep(0.02)
        raise AssertionError(f"the model never said {text!r} {count} times: {self.lines()}")

    def torque_off(self, *servo_ids: int) -> None:
        for servo_id in servo_ids:
            self.wait_for(f"servo {servo_id}: torque off")

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(10)


def app_copy(folder: Path, example: Path, name: str, timeout_ms: float = 1000.0, tty: Path | None = None,
             **replace: str) -> Path:
    """The example with the test's pty (``folder/bus.tty``, or ``tty``), a unique name and a long timeout (a
    loaded machine starves a pty's kernel worker for tens of ms), its module found where it lives."""
    text = example.read_text()
    text = text.replace(f'name = "{example.stem}"', f'name = "{unique_name(name)}"')
    port = next(line for line in text.splitlines() if line.startswith("port = "))
    text = text.replace(port, f'port = "{tty or folder / "bus.tty"}"')
    timeout = next(line for line in text.splitlines() if line.startswith("timeout_ms = "))
    text = text.replace(timeout, f"timeout_ms = {timeout_ms}")
    text = text.replace('"../jiwy/setpoints/step.csv"', f'"{EXAMPLES / "jiwy" / "setpoints" / "step.csv"}"')
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new)
    path = folder / example.name
    path.write_text(text)
    for module in example.parent.glob("*.py"):
        (folder / module.name).symlink_to(module)
    return path


def equal_up_to_the_first_miss(folder: Path, app_file: Path, duration_s: float) -> int:
    rtloop.run(load_app(app_file), duration_s, folder / "run")
    rtloop.simulate(load_app(app_file), duration_s, folder / "sim")
    miss_s = first_miss_s(folder / "run")
    compared, difference = compare_signals(folder / "run" / "signals.csv", folder / "sim" / "signals.csv", miss_s)
    assert difference is None, f"run and simulation differ at t = {difference} s (first miss at {miss_s} s)"
    assert compared >= 1
    return compared


def test_jiwy_on_dynamixel_servos_equals_its_simulation(tmp_path: Path) -> None:
    app_file = app_copy(tmp_path, JIWY, "jiwy_dxl_sim")
    model = Emulator(tmp_path, "--app", str(app_file))
    try:
        equal_up_to_the_first_miss(tmp_path, app_file, 1.0)
        model.torque_off(1, 2)  # the end of the run: torque off, confirmed by each servo
        assert len(model.wait_for("torque on")) == 2
    finally:
        model.stop()
    from rtloop.runtime.replay import replay

    replayed = replay(tmp_path / "run", tmp_path / "replay")  # the model is gone: the servos' readings play back
    assert replayed.equal and replayed.rows_compared > 0, replayed.divergence or replayed.cannot
    import numpy as np

    sim = np.genfromtxt(tmp_path / "sim" / "signals.csv", delimiter=",", names=True)
    assert abs(sim["aimpan_rad"][-1] - 0.5) < 0.01 and abs(sim["aimtilt_rad"][-1] - 0.3) < 0.01  # the step followed


def test_the_so100_arm_on_feetech_servos_equals_its_simulation(tmp_path: Path) -> None:
    app_file = app_copy(tmp_path, SO100, "so100_sim")
    model = Emulator(tmp_path, "--app", str(app_file))
    try:
        equal_up_to_the_first_miss(tmp_path, app_file, 0.8)
        model.torque_off(1, 2, 3, 4, 5, 6)
    finally:
        model.stop()


# --- a silent servo, a hardware error: the declared outcome ---------------------------------------------

def test_a_servo_gone_silent_is_a_fault_with_torque_off_at_the_others(tmp_path: Path) -> None:
    # on_missing = "fault" from the first sync read: the 19 answers before the silence must each come within
    # timeout_ms, so it outlasts a loaded machine's stall of the pty's kernel worker or the model (~150 ms)
    app_file = app_copy(tmp_path, JIWY, "jiwy_dxl_silent", timeout_ms=500.0,
                        **{'on_missing = "stale"': 'on_missing = "fault"'})
    model = Emulator(tmp_path, "--app", str(app_file), "--silent", "2@20")
    try:
        with pytest.raises(rtloop.TaskFailed, match=r"servo 2 \(tilt\) did not answer the sync read"):
            rtloop.run(load_app(app_file), 5.0, tmp_path / "run")
        model.torque_off(1)
    finally:
        model.stop()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert any("torque off not confirmed by servo 2 (tilt)" in note for note in summary["notes"]), summary["notes"]


def test_a_servo_gone_silent_is_stale_until_max_stale_in_a_row(tmp_path: Path) -> None:
    # a stall of the pty's kernel worker or the model (~150 ms on a loaded machine) before the silence must stay
    # short of 5 reads in a row: 5 x 100 ms
    app_file = app_copy(tmp_path, SO100, "so100_silent", timeout_ms=100.0,
                        **{"max_stale_in_a_row = 25 ": "max_stale_in_a_row = 5 "})
    model = Emulator(tmp_path, "--app", str(app_file), "--silent", "3@40")
    try:
        with pytest.raises(rtloop.TaskFailed, match=r"servo.* 3 \(elbow_flex\).* 5 reads in a row"):
            rtloop.run(load_app(app_file), 10.0, tmp_path / "run")
        model.torque_off(1, 2, 4, 5, 6)
    finally:
        model.stop()
    device = json.loads((tmp_path / "run" / "summary.json").read_text())["devices"]["arm"]
    assert device["stale_reads_by_source"].get("servo 3 (elbow_flex): no answer", 0) >= 4, device


def test_a_hardware_error_is_a_fault_by_default(tmp_path: Path) -> None:
    app_file = app_copy(tmp_path, JIWY, "jiwy_dxl_hw")
    model = Emulator(tmp_path, "--app", str(app_file), "--hardware-error", "1@30")
    try:
        with pytest.raises(rtloop.TaskFailed, match=r"servo 1 \(pan\) reports a hardware error: 0x20 \(overload\)"):
            rtloop.run(load_app(app_file), 5.0, tmp_path / "run")
        model.wait_for("servo 1: hardware error 0x20 (overload) at sync read 31: torque off")
        model.torque_off(2)
    finally:
        model.stop()


def test_a_hardware_error_reported_lets_the_run_go_on(tmp_path: Path) -> None:
    app_file = app_copy(tmp_path, JIWY, "jiwy_dxl_hw_report",
                        **{'safe_state = "torque_off"': 'safe_state = "torque_off"\non_hardware_error = "report"'})
    model = Emulator(tmp_path, "--app", str(app_file), "--hardware-error", "2@30")
    try:
        rtloop.run(load_app(app_file), 0.5, tmp_path / "run")
        model.wait_for("servo 2: hardware error 0x20")
        model.torque_off(1)
    finally:
        model.stop()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["stopped_by"].startswith("duration"), summary["stopped_by"]


# --- torque off on every way a run ends ------------------------------------------------------------------
# One model serves these four runs, one after the other (each starts it anew would cost a process start
# each): a run sets the goals where the servos are at activate, so where the last run left them does not
# matter; each test looks only at what the model said since its run began.

@pytest.fixture(scope="module")
def jiwy_model(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Emulator]:
    folder = tmp_path_factory.mktemp("jiwy_model")
    model = Emulator(folder, "--app", str(app_copy(folder, JIWY, "jiwy_dxl_model")))
    try:
        yield model
    finally:
        model.stop()


def _start(app_file: Path, out: Path) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "rtloop", "run", str(app_file), "--out", str(out), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_to_the_run_turns_the_torque_off(tmp_path: Path, jiwy_model: Emulator, stop: signal.Signals) -> None:
    app_file = app_copy(tmp_path, JIWY, f"jiwy_dxl_{stop.name.lower()}", tty=jiwy_model.link)
    jiwy_model.next_run()
    process = _start(app_file, tmp_path / "out")
    jiwy_model.wait_for("torque on", count=2)
    time.sleep(0.2)
    process.send_signal(stop)
    process.communicate(timeout=60)
    jiwy_model.torque_off(1, 2)


def test_a_nan_command_turns_the_torque_off(tmp_path: Path, jiwy_model: Emulator) -> None:
    app_file = app_copy(tmp_path, JIWY, "jiwy_dxl_nan", tty=jiwy_model.link,
                        **{'runnable = "pan_tilt:AimPanTilt"': 'runnable = "nan_aim:NanAfter20"'})
    (tmp_path / "nan_aim.py").write_text(
        "from pan_tilt import AimPanTilt\n\n\nclass NanAfter20(AimPanTilt):\n"
        "    def step(self, u, y):\n        super().step(u, y)\n"
        "        if self.tick.cycle >= 20:\n            y[1] = float('nan')\n")
    jiwy_model.next_run()
    with pytest.raises(rtloop.TaskFailed, match=r"gimbal\.u\[1\] \(tilt_position_rad\): command nan is not finite"):
        rtloop.run(load_app(app_file), 5.0, tmp_path / "run")
    jiwy_model.torque_off(1, 2)


def test_kill_9_of_the_task_the_supervisor_turns_the_torque_off(tmp_path: Path, jiwy_model: Emulator) -> None:
    app_file = app_copy(tmp_path, JIWY, "jiwy_dxl_kill", tty=jiwy_model.link)
    jiwy_model.next_run()
    process = _start(app_file, tmp_path / "out")
    jiwy_model.wait_for("torque on", count=2)
    os.kill(wait_for_the_task_pid(app_file, process), signal.SIGKILL)
    jiwy_model.torque_off(1, 2)
    process.communicate(timeout=60)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert any("turned the torque off on servos 1, 2" in note for note in summary["notes"]), summary["notes"]


# --- bad input: one line, exit 2 (3: a bus not ready) --------------------------------------------------

def _cli(app_file: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rtloop", "run", str(app_file), "--duration", "1",
                           "--out", str(app_file.parent / "out")], capture_output=True, text=True, timeout=120)


def test_servos_other_than_declared_are_one_line_exit_2_each(tmp_path: Path) -> None:
    """One model (servos 1 and 2, XM430-W350, servo 2's position limits 1700..2400 ticks), three apps that
    declare something else: an ID not on the bus, another model, a range outside the servo's limits."""
    model = Emulator(tmp_path, "dynamixel", "--servos", "1,2", "--model", "XM430-W350",
                     "--position-limits", "2:1700..2400")
    cases = [
        ({"id = 2,": "id = 3,"}, "devices.gimbal.servos[1].id: servo 3 (tilt) is not on the bus"),
        ({'{ name = "pan", id = 1, model = "XM430-W350"': '{ name = "pan", id = 1, model = "XL430-W250"'},
         "devices.gimbal.servos[0].model: servo 1 (pan) is a XM430-W350 (model number 1020); the app says "
         "XL430-W250 (1060)"),
        ({}, "devices.gimbal.servos[1].range_rad: [-0.8, 0.8] rad is ticks 1527..2569; servo 2 (tilt) allows "
         "1700..2400"),
    ]
    try:
        for index, (replace, words) in enumerate(cases):
            folder = tmp_path / f"app{index}"
            folder.mkdir()
            result = _cli(app_copy(folder, JIWY, "jiwy_dxl_mismatch", tty=model.link, **replace))
            assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
            assert words in result.stderr, result.stderr
    finally:
        model.stop()


def test_two_devices_on_one_port_are_one_line_exit_2(tmp_path: Path) -> None:
    text = JIWY.read_text()
    second = text[text.index("[devices.gimbal]"):text.index("[devices.gimbal.limits")]
    second = second.replace("[devices.gimbal]", "[devices.gimbal2]").replace("id = 1,", "id = 3,").replace(
        "id = 2,", "id = 4,")
    app_file = app_copy(tmp_path, JIWY, "jiwy_dxl_two")
    port = next(line for line in app_file.read_text().splitlines() if line.startswith("port = "))
    second = "\n".join(port if line.startswith("port = ") else line for line in second.splitlines())
    app_file.write_text(app_file.read_text() + "\n" + second + "\n")
    result = _cli(app_file)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert f"devices.gimbal2.port: serial line {tmp_path / 'bus.tty'} is also held by devices.gimbal.port" \
        in result.stderr


def test_a_range_outside_one_turn_is_one_line_exit_2_at_load(tmp_path: Path) -> None:
    app_file = app_copy(tmp_path, JIWY, "jiwy_dxl_range", **{"range_rad = [-1.6, 1.6]": "range_rad = [-3.5, 3.5]"})
    result = _cli(app_file)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "devices.gimbal.servos[0].range_rad: [-3.5, 3.5] rad is ticks -233..4329 around zero_ticks 2048: " \
           "outside the servo's 0..4095" in result.stderr


def test_a_bus_where_nothing_answers_is_not_ready_exit_3(tmp_path: Path) -> None:
    master, slave = os.openpty()  # a line with nothing on it: an adapter without power on the servos
    try:
        (tmp_path / "bus.tty").symlink_to(os.ttyname(slave))
        app_file = app_copy(tmp_path, JIWY, "jiwy_dxl_silent_bus", timeout_ms=5.0)
        result = _cli(app_file)
    finally:
        os.close(master)
        os.close(slave)
    assert result.returncode == 3 and result.stderr.count("\n") == 1, result.stderr
    assert "devices.gimbal.port: no servo answered" in result.stderr


# --- the model speaks the real protocol: ROBOTIS's own SDK talks to it ------------------------------------

def test_dynamixel_sdk_pings_sync_writes_and_sync_reads_the_model(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """The model answers ROBOTIS's own SDK. What is checked is the protocol, not the model's speed: the SDK
    gives a reply 2 x its USB latency timer (16 ms) + 2 ms, and on a loaded 2-core machine the model's
    process was once scheduled later than that (COMM_RX_TIMEOUT). Here the SDK waits up to 1 s."""
    sdk = pytest.importorskip("dynamixel_sdk", reason="dynamixel-sdk is not installed (the test extra has it)")
    monkeypatch.setattr(sdk.port_handler, "LATENCY_TIMER", 499)  # (499 * 2 + 2) ms = 1 s per reply
    model = Emulator(tmp_path, "dynamixel", "--servos", "1,2", "--model", "XM430-W350")
    try:
        port = sdk.PortHandler(os.path.realpath(model.link))
        assert port.openPort() and port.setBaudRate(1_000_000)
        packets = sdk.Protocol2PacketHandler()
        assert packets.ping(port, 2)[:2] == (1020, sdk.COMM_SUCCESS)  # XM430-W350's model number
        assert packets.write1ByteTxRx(port, 1, 64, 1)[0] == sdk.COMM_SUCCESS  # torque on
        model.wait_for("servo 1: torque on")
        writes = sdk.GroupSyncWrite(port, packets, 116, 4)
        writes.addParam(1, list((2048 + 512).to_bytes(4, "little")))
        writes.addParam(2, list((2048).to_bytes(4, "little")))
        reads = sdk.GroupSyncRead(port, packets, 126, 10)
        reads.addParam(1)
        reads.addParam(2)
        for _ in range(300):  # 300 periods of 2 ms: the servo gets there
            assert writes.txPacket() == sdk.COMM_SUCCESS
            assert reads.txRxPacket() == sdk.COMM_SUCCESS
        assert abs(reads.getData(1, 132, 4) - 2560) <= 1 and reads.getData(2, 132, 4) == 2048
        port.closePort()
    finally:
        model.stop()


def test_the_servo_cycle_benchmark_runs_and_allocates_nothing_that_stays(tmp_path: Path) -> None:
    """benchmarks/bench_servos.py at its smallest (without dynamixel-sdk's 2-4 ms cycles): its table is there,
    the C checks and the Python references both ran, and tracemalloc finds no byte kept by rtloop/io over the
    cycles of TaskDevices.at_release with a 6-servo bus (timings unchecked)."""
    result = subprocess.run([sys.executable, str(EXAMPLES.parent / "benchmarks" / "bench_servos.py"),
                             "--cycles", "300", "--rounds", "1", "--without-sdk", "--json", str(tmp_path / "r.json")],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "| rtloop vs os calls |" in result.stdout and "| framework vs os calls |" in result.stdout
    results = json.loads((tmp_path / "r.json").read_text())
    assert results["allocated_bytes_io"] <= 0
    from rtloop.io.compiled import devio

    assert results["checks_in_c"] is (devio() is not None)
    if results["checks_in_c"]:  # the Python references' batches ran too
        assert "| host share: C part vs Python references |" in result.stdout
        assert "reference_us" in results["results"]["rtloop vs os calls"]


def test_a_port_relative_to_the_app_file_is_named_without_dot_dots() -> None:
    # a fault said "did not answer the sync read on /…/examples/so100_feetech/../../runs/so100.tty"
    app = load_app(SO100)
    assert app.devices["arm"].device.config["port"] == str(EXAMPLES.parent / "runs" / "so100.tty")
    from rtloop.app.appfile import _from_folder

    assert _from_folder(Path("/a/b"), "../../c/tty") == "/c/tty" and _from_folder(Path("/a/b"), "tty") == "/a/b/tty"
    assert _from_folder(Path("/a/b"), "link/../tty") == "/a/b/link/../tty"  # past a name: that name may be a link
