"""Two apps on two "hosts": network namespaces joined by a veth pair, talking ROS 2 over DDS.

The sensor app (examples/two_apps/sensor.toml) runs in one namespace, the controller app in
the other; their only link is a virtual Ethernet cable, so what the controller records
crossed a network as between two devices (the thesis's multi-device case). With
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` on both, nothing crosses. Needs root (to make
namespaces) and ``ip`` (iproute2); skipped otherwise. /dev/shm is shared between the
namespaces, so the apps get names of their own.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import skip_in_rtkernel_guest
from rtloop.ipc.channels import LatestValue
from rtloop.ipc.ports import running_apps
from rtloop.ipc.schema import PortWord
from test_ros_app import TWO_APPS, random_domain, signals_of, summary_of

pytest.importorskip("cyclonedds")

pytestmark = skip_in_rtkernel_guest(
    "two apps in two network namespaces talking DDS over a veth pair is host networking, not the RT "
    "kernel or a driver; discovery across the pair and the runs are bounded by seconds of the host's "
    "time, which emulation (~20x slower) cannot keep"
)

ROOT = Path(__file__).resolve().parents[1]


def namespaces_unavailable() -> str:
    if os.geteuid() != 0:
        return "needs root to create network namespaces"
    if shutil.which("ip") is None:
        return "needs the ip command (iproute2)"
    probe = f"rtlprobe{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode:
        return f"cannot create a network namespace here: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return ""


def ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


@pytest.fixture
def host_pairs():
    """Makes pairs of network namespaces, each pair joined by its own veth cable; removes them all after."""
    reason = namespaces_unavailable()
    if reason:
        pytest.skip(reason)
    made: list[str] = []

    def pair() -> list[str]:
        tag = f"{os.getpid() % 10000}{random.randint(0, 99)}{len(made) // 2}"
        hosts = [f"rtl{tag}a", f"rtl{tag}b"]
        subnet = f"10.{random.randint(64, 250)}.{random.randint(0, 250)}"
        for host in hosts:
            ip("netns", "add", host)
            made.append(host)
        ip("link", "add", f"v{tag}a", "netns", hosts[0], "type", "veth", "peer", "name", f"v{tag}b", "netns", hosts[1])
        for index, host in enumerate(hosts):
            device = f"v{tag}{'ab'[index]}"
            ip("-n", host, "addr", "add", f"{subnet}.{index + 1}/24", "dev", device)
            ip("-n", host, "link", "set", "lo", "up")
            ip("-n", host, "link", "set", device, "up")
            ip("-n", host, "route", "add", "224.0.0.0/4", "dev", device)  # DDS discovery is multicast
        return hosts

    try:
        yield pair
    finally:
        for host in made:
            subprocess.run(["ip", "netns", "del", host], capture_output=True)


def app_copy(source: Path, folder: Path, name: str) -> Path:
    text = source.read_text()
    original = next(line for line in text.splitlines() if line.startswith("name = "))
    target = folder / source.name
    target.write_text(text.replace(original, f'name = "{name}"'))
    return target


def run_in(host: str, app_file: Path, out: Path, env: dict[str, str]) -> subprocess.Popen:
    """``rtloop run`` in namespace ``host``, until stopped. Its duration is only a bound, past the test's
    120 s wait for samples to cross: a run of 60 s could end inside it (four runs and their bridges start
    at once, each a Python that imports DDS: seconds on a loaded machine), failing as "a run ended"."""
    return subprocess.Popen(["ip", "netns", "exec", host, sys.executable, "-m", "rtloop.cli", "run", str(app_file),
                             "--duration", "200", "--out", str(out), "--quiet"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def port_writes(name: str, port: str) -> int:
    """How many values the app's input ``port`` has taken so far (its bridge writes each sample it receives)."""
    app = next((app for app in running_apps() if app.name == name), None)
    if app is None:
        return -1
    segment = app.segment(app.ports[port]["segment"])
    try:
        return int(LatestValue(segment).words[PortWord.WRITES])
    finally:
        segment.close()


def apps_running(names: list[str]) -> bool:
    found = {app.name: app for app in running_apps()}
    return all(name in found and all(found[name].task_pids().values()) for name in names)


@pytest.mark.rt
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_two_apps_in_two_network_namespaces(tmp_path: Path, host_pairs) -> None:
    """Two pairs at once, one with ``SUBNET`` discovery, one with ``LOCALHOST``: samples cross the
    first pair's cable; none cross the second's while it runs at least as long as the first pair
    needed to find each other, plus 3 s (when 300 samples have crossed there)."""
    ranges = ("SUBNET", "LOCALHOST")
    suffix = f"{os.getpid()}_{random.randint(0, 999)}"
    names = {r: (f"sensor_{suffix}{r[0]}", f"controller_{suffix}{r[0]}") for r in ranges}
    runs: dict[str, list[subprocess.Popen]] = {}
    for index, discovery_range in enumerate(ranges):
        hosts, folder = host_pairs(), tmp_path / discovery_range
        folder.mkdir()
        sensor = app_copy(TWO_APPS / "sensor.toml", folder, names[discovery_range][0])
        controller = app_copy(TWO_APPS / "controller.toml", folder, names[discovery_range][1])
        env = {**os.environ, "ROS_DOMAIN_ID": str((random_domain() + 50 * index) % 101 + 1),
               "ROS_AUTOMATIC_DISCOVERY_RANGE": discovery_range,
               "PYTHONPATH": os.pathsep.join([str(TWO_APPS), str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
        runs[discovery_range] = [run_in(hosts[1], controller, folder / "controller", env),
                                 run_in(hosts[0], sensor, folder / "sensor", env)]
    try:
        running_since: dict[str, float] = {}
        crossed_after_s = None
        deadline = time.monotonic() + 120  # bridges start in seconds on a busy machine
        while time.monotonic() < deadline:
            for discovery_range in ranges:
                if discovery_range not in running_since and apps_running(list(names[discovery_range])):
                    running_since[discovery_range] = time.monotonic()
            for run in (*runs["SUBNET"], *runs["LOCALHOST"]):
                assert run.poll() is None, run.communicate()[1]
            crossed = port_writes(names["SUBNET"][1], "sensor") if "SUBNET" in running_since else 0
            if crossed > 0 and crossed_after_s is None:
                crossed_after_s = time.monotonic() - running_since["SUBNET"]
            if (crossed >= 300 and "LOCALHOST" in running_since
                    and time.monotonic() - running_since["LOCALHOST"] >= crossed_after_s + 3):
                break
            time.sleep(0.1)
        else:
            pytest.fail(f"in 120 s {crossed} samples crossed (300 wanted); apps running: {sorted(running_since)}")
    finally:
        for order in (0, 1):  # the controllers first: what they recorded, the sensors recorded sending
            for discovery_range in ranges:
                run = runs[discovery_range][order]
                if run.poll() is None:
                    run.send_signal(signal.SIGINT)
        for run in (*runs["SUBNET"], *runs["LOCALHOST"]):
            try:
                run.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                run.kill()
                run.communicate()
    for discovery_range in ranges:
        for run in runs[discovery_range]:
            assert run.returncode == 0, run.stderr
    for discovery_range in ranges:
        folder = tmp_path / discovery_range
        header, rows = signals_of(folder / "controller")
        stamps = rows[:, header.index("monitor.t_s")]
        received = stamps[stamps > 0]
        if discovery_range == "LOCALHOST":
            assert len(received) == 0, "LOCALHOST discovery must not reach the other namespace"
            continue
        assert len(np.unique(received)) > 100, f"only {len(np.unique(received))} samples crossed"
        sensor_header, sensor_rows = signals_of(folder / "sensor")
        sent = set(zip(sensor_rows[:, sensor_header.index("sine.t_s")].round(9).tolist(),
                       sensor_rows[:, sensor_header.index("sine.value")].tolist(), strict=True))
        values = rows[:, header.index("monitor.value")][stamps > 0]
        pairs = set(zip(received.round(9).tolist(), values.tolist(), strict=True))
        assert pairs <= sent, "the controller recorded samples the sensor never sent"
        bridge = summary_of(folder / "controller")["bridges"]["subscribe /two_apps/sensor"]
        assert bridge["state"] == "ok" and bridge["accepted"] > 100
