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
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import skip_in_rtkernel_guest
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
def two_hosts():
    reason = namespaces_unavailable()
    if reason:
        pytest.skip(reason)
    tag = f"{os.getpid() % 10000}{random.randint(0, 99)}"
    hosts = [f"rtl{tag}a", f"rtl{tag}b"]
    subnet = f"10.{random.randint(64, 250)}.{random.randint(0, 250)}"
    for host in hosts:
        ip("netns", "add", host)
    try:
        ip("link", "add", f"v{tag}a", "netns", hosts[0], "type", "veth", "peer", "name", f"v{tag}b",
           "netns", hosts[1])
        for index, host in enumerate(hosts):
            device = f"v{tag}{'ab'[index]}"
            ip("-n", host, "addr", "add", f"{subnet}.{index + 1}/24", "dev", device)
            ip("-n", host, "link", "set", "lo", "up")
            ip("-n", host, "link", "set", device, "up")
            ip("-n", host, "route", "add", "224.0.0.0/4", "dev", device)  # DDS discovery is multicast
        yield hosts
    finally:
        for host in hosts:
            subprocess.run(["ip", "netns", "del", host], capture_output=True)


def app_copy(source: Path, folder: Path, name: str) -> Path:
    text = source.read_text()
    original = next(line for line in text.splitlines() if line.startswith("name = "))
    target = folder / source.name
    target.write_text(text.replace(original, f'name = "{name}"'))
    return target


def run_in(host: str, app_file: Path, out: Path, duration_s: float, env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen(["ip", "netns", "exec", host, sys.executable, "-m", "rtloop.cli", "run", str(app_file),
                             "--duration", str(duration_s), "--out", str(out), "--quiet"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.rt
@pytest.mark.slow
@pytest.mark.parametrize("discovery_range", ["SUBNET", "LOCALHOST"])
def test_two_apps_in_two_network_namespaces(tmp_path: Path, two_hosts: list[str], discovery_range: str) -> None:
    suffix = f"{os.getpid()}_{random.randint(0, 9999)}"
    sensor = app_copy(TWO_APPS / "sensor.toml", tmp_path, f"sensor_{suffix}")
    controller = app_copy(TWO_APPS / "controller.toml", tmp_path, f"controller_{suffix}")
    env = {**os.environ, "ROS_DOMAIN_ID": str(random_domain()), "ROS_AUTOMATIC_DISCOVERY_RANGE": discovery_range,
           "PYTHONPATH": os.pathsep.join([str(TWO_APPS), str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    runs = [run_in(two_hosts[1], controller, tmp_path / "controller", 20, env),
            run_in(two_hosts[0], sensor, tmp_path / "sensor", 16, env)]  # bridges start in seconds on a busy machine
    for run in runs:
        try:
            _, stderr = run.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            run.kill()
            _, stderr = run.communicate()
        assert run.returncode == 0, stderr
    header, rows = signals_of(tmp_path / "controller")
    stamps = rows[:, header.index("monitor.t_s")]
    received = stamps[stamps > 0]
    if discovery_range == "LOCALHOST":
        assert len(received) == 0, "LOCALHOST discovery must not reach the other namespace"
        return
    assert len(np.unique(received)) > 100, f"only {len(np.unique(received))} samples crossed"
    sensor_header, sensor_rows = signals_of(tmp_path / "sensor")
    sent = set(zip(sensor_rows[:, sensor_header.index("sine.t_s")].round(9).tolist(),
                   sensor_rows[:, sensor_header.index("sine.value")].tolist(), strict=True))
    values = rows[:, header.index("monitor.value")][stamps > 0]
    pairs = set(zip(received.round(9).tolist(), values.tolist(), strict=True))
    assert pairs <= sent, "the controller recorded samples the sensor never sent"
    bridge = summary_of(tmp_path / "controller")["bridges"]["subscribe /two_apps/sensor"]
    assert bridge["state"] == "ok" and bridge["accepted"] > 100
