"""The scope pin and the E-stop in whole runs, on gpio-sim in the PREEMPT_RT test guest.

- The scope pin toggles exactly once per cycle: every value the task sets on the line is
  counted by tracing its ioctls with strace (exact, whatever the guest's speed; not through the
  kernel's ``gpio:gpio_value`` trace event, which hung the emulated guest now and then), for the
  compiled hot path and its Python twin.
- An E-stop edge stops the app: every output at its safe value, within one period of the
  edge's kernel timestamp plus the task's wake-up, said in summary.json.
"""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from io_guest_devices import SimLine, guest_device, scope_values

APP = """name = "{name}"
[tasks.ctl]
runnable = "rt_test_runnables:Gain"
args = {{ n = 2, gain = 0.0, offset = 1.0 }}
period_ns = {period_ns}
priority = 70

[devices.panel]
kind = "gpio"
task = "ctl"
chip = "{chip}"
outputs = ["led", "enable"]
{extra}

[[connect]]
from = "ctl.y[0:2]"
to = "panel.u[0:2]"
"""


def run_app(tmp_path: Path, text: str, *args: str, env: dict | None = None,
            wrapper: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    app = tmp_path / "app.toml"
    app.write_text(text)
    tests = str(Path(__file__).resolve().parent)
    env = {**os.environ, **(env or {}), "PYTHONPATH": os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([*wrapper, sys.executable, "-m", "rtloop", "run", str(app), "--out", str(tmp_path / "run"),
                           "-q", *args], capture_output=True, text=True, timeout=600, env=env)


@pytest.mark.rtkernel
@pytest.mark.timeout(1200)
@pytest.mark.parametrize("hot_path", ["c", "python"])
@pytest.mark.parametrize("mode", ["toggle", "step"])
def test_the_scope_pin_changes_exactly_as_often_as_the_cycles_say(tmp_path, hot_path, mode):
    """Every value the task sets on the scope pin, counted by tracing its ioctls with strace: exact
    whatever the guest's speed, and without the kernel's ``gpio:gpio_value`` trace event (with it
    on, the emulated guest hung now and then: docs/rtkernel-guest.md)."""
    gpio = guest_device("gpio")
    strace = shutil.which("strace")
    if strace is None:
        pytest.skip("no strace here (needed to count the scope pin's edges exactly)")
    text = APP.format(name=f"scope_{mode}_{hot_path}_{os.getpid()}", period_ns=20_000_000, chip=gpio["device"],
                      extra=f'scope_pin = "scope"\nscope_mode = "{mode}"')
    traces = tmp_path / "strace" / "ioctl"
    traces.parent.mkdir()
    # -ff: one file per process and thread (no interleaved, unfinished calls); seccomp-bpf: the
    # traced processes stop at their ioctls only, not at every system call
    run = run_app(tmp_path, text, "--duration", "10", env={"RTLOOP_PURE_PYTHON": "1" if hot_path == "python" else "0"},
                  wrapper=(strace, "-ff", "-qq", "--seccomp-bpf", "-e", "trace=ioctl", "-e", "signal=none",
                           "-o", str(traces)))
    assert run.returncode == 0, run.stderr
    # configure requests the pin low (through the chip's GET_LINE ioctl, not SET_VALUES): what
    # follows are the cycles' values
    values = scope_values(traces)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    cycles = summary["tasks"]["ctl"]["cycles"]
    assert summary["hot_path"] == hot_path
    assert cycles > 10
    if mode == "toggle":  # one edge per release, alternating
        assert len(values) == cycles and values == [(i + 1) % 2 for i in range(cycles)], (len(values), cycles)
    else:  # high at the start of step, low when it ended
        assert values == [1, 0] * cycles, (len(values), cycles)


@pytest.mark.rtkernel
@pytest.mark.timeout(1200)
def test_an_estop_edge_stops_the_app_with_every_output_safe(tmp_path):
    gpio = guest_device("gpio")
    pytest.importorskip("gpiod")
    estop, led, enable = (SimLine(gpio, n) for n in ("estop", "led", "enable"))
    estop.pull(True)  # released
    period_ns = 50_000_000
    text = APP.format(name=f"estop_{os.getpid()}", period_ns=period_ns, chip=gpio["device"],
                      extra='estop = "estop"\nestop_edge = "falling"')
    app = tmp_path / "app.toml"
    app.write_text(text)
    tests = str(Path(__file__).resolve().parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")])}
    process = subprocess.Popen([sys.executable, "-m", "rtloop", "run", str(app), "--duration", "300", "--out",
                                str(tmp_path / "run"), "-q"], env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        if led.wait_value(1, timeout_s=600) != 1 or enable.value != 1:  # start-up in an emulated guest
            process.kill()
            pytest.fail(f"the app never drove its outputs: {process.communicate()}")
        time.sleep(0.5)
        estop.pull(False)  # pressed
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
        estop.pull(True)
    assert process.returncode == 0, stderr
    assert (led.value, enable.value) == (0, 0)  # safe
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert "E-stop: falling edge on line 'estop' of device 'panel'" in summary["stopped_by"]
    note = next(n for n in summary["notes"] if n.startswith("E-stop: edge at"))
    edge_ns, safe_ns = map(int, re.search(r"edge at (\d+) ns.*safe at (\d+) ns", note).groups())
    stop_cycle = int(re.search(r"at cycle (\d+)", summary["stopped_by"]).group(1))
    with open(tmp_path / "run" / "timing.csv") as timing:
        releases = {int(row["cycle"]): int(row["release_ns"]) for row in csv.DictReader(timing)}
    ran_before = max(cycle for cycle in releases if cycle < stop_cycle)
    # The stop came at the first release the task ran after the edge (the one it ran before saw no
    # edge; a loaded guest may skip releases after a late cycle, and they read nothing), and the
    # safe values followed in that cycle: within one period of the edge plus the task's wake-up and
    # its reads and writes, whatever this emulated machine's speed.
    assert releases[ran_before] <= edge_ns < safe_ns, (summary["stopped_by"], note, ran_before, stop_cycle)


@pytest.mark.rtkernel
@pytest.mark.timeout(1200)
def test_bad_input_in_the_guest_is_one_line_exit_2_nothing_started(tmp_path):
    gpio = guest_device("gpio")
    import gpiod

    text = APP.format(name=f"busy_{os.getpid()}", period_ns=20_000_000, chip=gpio["device"], extra="")
    with gpiod.Chip(gpio["device"]) as chip:
        holder = chip.request_lines({"led": None}, consumer="another-program")
        try:
            run = run_app(tmp_path, text, "--duration", "1")
        finally:
            holder.release()
    assert run.returncode == 3 and len(run.stderr.strip().splitlines()) == 1, run.stderr  # a device not ready
    assert "devices.panel.outputs: line 'led'" in run.stderr and "busy" in run.stderr
    assert not (tmp_path / "run").exists()

    vcan = guest_device("vcan")
    can_app = (f'name = "nocan_{os.getpid()}"\n[tasks.ctl]\nrunnable = "rt_test_runnables:Gain"\n'
               'period_ns = 20_000_000\n[devices.drive]\nkind = "can"\ntask = "ctl"\ninterface = "can9"\n'
               'send = [{ id = 0x200 }]\n')
    run = run_app(tmp_path, can_app, "--duration", "1")
    assert run.returncode == 3 and len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert "devices.drive.interface: no network interface 'can9'" in run.stderr and vcan["interface"] in run.stderr
    assert not (tmp_path / "run").exists()

    spi = guest_device("spi")
    import pwd

    try:
        nobody = pwd.getpwnam("nobody")
    except KeyError:
        pytest.skip("no user 'nobody' to try a device without permission")
    spi_app = (f'name = "noperm_{os.getpid()}"\n[tasks.ctl]\nrunnable = "rt_test_runnables:Gain"\n'
               f'period_ns = 20_000_000\n[devices.fpga]\nkind = "spi"\ntask = "ctl"\ndevice = "{spi["devices"][0]}"\n'
               'length = 8\n')
    folder = Path(tempfile.mkdtemp(prefix="rtloop-nobody-"))  # pytest's tmp_path is root's alone
    os.chown(folder, nobody.pw_uid, nobody.pw_gid)
    (folder / "app.toml").write_text(spi_app)
    tests = str(Path(__file__).resolve().parent)
    env = {**os.environ, "HOME": str(folder), "PYTHONPATH": os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, "-m", "rtloop", "run", str(folder / "app.toml"), "--duration", "1",
                          "--out", str(folder / "run"), "-q"], capture_output=True, text=True, timeout=600, env=env,
                         user=nobody.pw_uid, group=nobody.pw_gid, cwd=folder)
    assert run.returncode == 3 and len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert f"devices.fpga.device: no permission to open {spi['devices'][0]}" in run.stderr
    assert not (folder / "run").exists()
