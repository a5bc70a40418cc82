"""ROS 2 interoperability over DDS: rtloop publishes, an independent process receives.

The receiving side is a plain cyclonedds program that declares the ROS 2 types itself
(``pkg::msg::dds_::Type_``) exactly as a ROS 2 node's type support would, without
importing rtloop: it only matches if rtloop uses the ROS 2 topic and type names and
field layout. Each test uses its own random ``ROS_DOMAIN_ID`` so runs do not mix, and
bounds every wait; each wait ends at the event it waits for (a test takes a second or two).
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import textwrap
import threading
import time

import pytest

from conftest import find_cyclonedds_cli, random_ros_domain
from ros2_peer_types import ROS2_TYPES

pytest.importorskip("cyclonedds")

from rtloop.ros.dds import RosPublisher, RosSubscriber, dds_topic_name
from rtloop.ros.errors import RosConfigError, domain_id_from_env
from rtloop.ros.messages import JointState, float64_multi_array, joint_state

# Bounds, not expectations: a Python process that imports DDS (the receiver, the cyclonedds CLI) took
# more than 10 s to start on the 2-core machine under load, and discovery in this process's own
# participants can wait as long for a descheduled DDS thread. Every wait ends at its event.
START_TIMEOUT_S = 60.0
DISCOVERY_TIMEOUT_S = 30.0

# A ROS 2 node written by someone else: its own type declarations, plain cyclonedds.
RECEIVER = textwrap.dedent(
    """
    import json, sys
    from dataclasses import dataclass, field
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration
    """
) + ROS2_TYPES + textwrap.dedent(
    """

    domain, topic, kind = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    data_type = {"JointState": JointState_, "Float64MultiArray": Float64MultiArray_}[kind]
    participant = DomainParticipant(domain)
    qos = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5))
    reader = DataReader(participant, Topic(participant, topic, data_type), qos=qos)
    print("READY", flush=True)
    sample = reader.take_one(timeout=duration(seconds=float(sys.argv[4])))
    # XTypes matching ignores type names, but rmw_cyclonedds and Fast DDS do not:
    # report the name the publisher announced so the test can check it.
    announced = sorted({reader.get_matched_publication_data(h).type_name
                        for h in reader.get_matched_publications()})

    def plain(value):
        if hasattr(value, "__dataclass_fields__"):
            return {k: plain(getattr(value, k)) for k in value.__dataclass_fields__}
        if isinstance(value, list):
            return [plain(v) for v in value]
        if isinstance(value, float):
            return {"hex": value.hex()}
        return value

    print(json.dumps({"sample": plain(sample), "type_names": announced}), flush=True)
    """
)


def random_domain() -> int:
    """A domain id for one test; ROS 2 uses 0..101, we avoid 0 (the default), and a parallel run's
    workers draw from sets of their own (conftest.random_ros_domain)."""
    return random_ros_domain()


def receive_in_other_process(domain: int, dds_topic: str, kind: str, publish) -> dict:
    """Start :data:`RECEIVER`, call ``publish()`` until it reports a sample, return it.

    Also checks that the publisher announced the ROS 2 DDS type name of ``kind``.
    """
    child = subprocess.Popen(
        [sys.executable, "-c", RECEIVER, str(domain), dds_topic, kind, str(DISCOVERY_TIMEOUT_S)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(line) for line in child.stdout],
                     daemon=True).start()
    try:
        assert lines.get(timeout=START_TIMEOUT_S).strip() == "READY"
        # Best effort: keep publishing until the receiver has one sample (its reader waits as long).
        deadline = time.monotonic() + DISCOVERY_TIMEOUT_S
        while time.monotonic() < deadline:
            publish()
            try:
                report = json.loads(lines.get(timeout=0.05))
            except queue.Empty:
                continue
            package = "sensor_msgs" if kind == "JointState" else "std_msgs"
            assert report["type_names"] == [f"{package}::msg::dds_::{kind}_"]
            return report["sample"]
        pytest.fail(f"no sample received on {dds_topic} within {DISCOVERY_TIMEOUT_S} s")
    finally:
        child.kill()
        _, stderr = child.communicate(timeout=5)
        if child.returncode not in (0, -9):
            print(stderr)


def test_joint_state_reaches_independent_ros2_reader():
    domain = random_domain()
    names = ["pan", "tilt"]
    positions = [0.1 + 0.2, -1e-310]  # an inexact sum and a subnormal: bit-for-bit check
    stamp_ns = 1_700_000_000_123_456_789
    with RosPublisher("/jiwy/angles", JointState, domain_id=domain) as pub:
        msg = joint_state(names, positions, stamp_ns)
        got = receive_in_other_process(domain, "rt/jiwy/angles", "JointState",
                                       lambda: pub.publish(msg))
    assert got["header"] == {"stamp": {"sec": 1_700_000_000, "nanosec": 123_456_789},
                             "frame_id": ""}
    assert got["name"] == names
    assert got["position"] == [{"hex": v.hex()} for v in positions]
    assert got["velocity"] == [] and got["effort"] == []


def test_float64_multi_array_reaches_independent_ros2_reader():
    domain = random_domain()
    values = [1.0, -0.0, float.fromhex("0x1.fffffffffffffp+1023"), 5e-324, 1 / 3]
    with RosPublisher("setpoint", "std_msgs/msg/Float64MultiArray", domain_id=domain,
                      qos="sensor") as pub:
        msg = float64_multi_array(values, label="u")
        got = receive_in_other_process(domain, "rt/setpoint", "Float64MultiArray",
                                       lambda: pub.publish(msg))
    assert got["data"] == [{"hex": v.hex()} for v in values]
    assert got["layout"] == {"dim": [{"label": "u", "size": 5, "stride": 5}],
                             "data_offset": 0}


@pytest.mark.parametrize("qos", ["sensor", "reliable"])
def test_subscriber_take_is_non_blocking_and_returns_in_order(qos):
    domain = random_domain()
    with (
        RosSubscriber("/jiwy/setpoint", "std_msgs/msg/Float64MultiArray", qos=qos,
                      domain_id=domain) as sub,
        RosPublisher("/jiwy/setpoint", "std_msgs/msg/Float64MultiArray", qos=qos,
                     domain_id=domain) as pub,
    ):
        assert sub.take() == []
        assert pub.wait_for_subscribers(1, timeout_s=DISCOVERY_TIMEOUT_S)
        assert sub.wait_for_publishers(1, timeout_s=DISCOVERY_TIMEOUT_S)
        for k in range(4):
            pub.publish(float64_multi_array([k, 2.0 * k]))
        received = []
        deadline = time.monotonic() + DISCOVERY_TIMEOUT_S
        while len(received) < 4 and time.monotonic() < deadline:
            sub.wait(0.5)
            received += sub.take()
        assert [m.data for m in received] == [[k, 2.0 * k] for k in range(4)]
        # Nothing is pending: take() returns at once, empty. A take that blocked would return the message
        # published 2 s from now (a logical check: a loaded machine may run this thread late by tens of ms).
        cancel, late = threading.Event(), threading.Event()

        def publish_later() -> None:
            if not cancel.wait(2.0):
                late.set()
                pub.publish(float64_multi_array([9.0]))

        publisher = threading.Thread(target=publish_later)
        publisher.start()
        try:
            assert sub.take() == [] and not late.is_set()
        finally:
            cancel.set()
            publisher.join()


def test_other_domain_does_not_receive():
    domain = random_domain()
    other = domain + 101  # 102..202: still a valid DDS domain, never random_domain()
    with (
        RosSubscriber("/jiwy/angles", JointState, domain_id=other) as sub,
        RosPublisher("/jiwy/angles", JointState, domain_id=domain) as pub,
    ):
        for k in range(5):
            pub.publish(joint_state(["a"], [k], 0))
        assert not sub.wait(0.3)
        assert sub.take() == []


def test_cyclonedds_cli_prints_values_from_running_publisher():
    """`cyclonedds subscribe` discovers the type over XTypes; no type name needed."""
    cli = find_cyclonedds_cli()
    if cli is None:
        pytest.skip("the cyclonedds CLI is not on PATH")
    domain = random_domain()
    stop = threading.Event()
    pub = RosPublisher("/jiwy/angles", JointState, domain_id=domain)

    def publish_forever():
        while not stop.is_set():
            pub.publish(joint_state(["pan", "tilt"], [0.75, -1.25], 42))
            time.sleep(0.05)

    publisher = threading.Thread(target=publish_forever, daemon=True)
    publisher.start()
    child = subprocess.Popen(
        [cli, "subscribe", "rt/jiwy/angles", "--id", str(domain), "--type", "scan-random",
         "--qos", "scan-random", "--suppress-progress-bar", "--color", "none"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "200"},
    )
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(line) for line in child.stdout],
                     daemon=True).start()
    seen = []
    try:
        deadline = time.monotonic() + START_TIMEOUT_S  # the CLI starts Python and imports DDS
        while time.monotonic() < deadline:
            try:
                seen.append(lines.get(timeout=0.1))
            except queue.Empty:
                continue
            if "position=[0.75, -1.25]" in seen[-1]:
                break
        else:
            pytest.fail("cyclonedds subscribe printed no sample:\n" + "".join(seen))
    finally:
        stop.set()
        child.kill()
        child.communicate(timeout=5)
        publisher.join(timeout=2)
        pub.close()
    text = "".join(seen)
    assert "JointState_(" in text
    assert "name=['pan', 'tilt']" in text
    assert "nanosec=42" in text


def test_topic_names_are_mangled_like_ros2():
    assert dds_topic_name("/jiwy/angles") == "rt/jiwy/angles"
    assert dds_topic_name("jiwy/angles") == "rt/jiwy/angles"
    assert dds_topic_name("/setpoint_1") == "rt/setpoint_1"
    for bad in ["", "/", "/a/", "/a//b", "/1a", "/a b", "/a__b", "~/x", "/a-b"]:
        with pytest.raises(RosConfigError):
            dds_topic_name(bad)


def test_domain_id_from_environment(monkeypatch):
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    assert domain_id_from_env() == 0
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert domain_id_from_env() == 42
    assert domain_id_from_env(7) == 7
    monkeypatch.setenv("ROS_DOMAIN_ID", "forty")
    with pytest.raises(RosConfigError, match="ROS_DOMAIN_ID"):
        domain_id_from_env()
    with pytest.raises(RosConfigError, match="outside"):
        domain_id_from_env(500)


def test_publisher_uses_ros_domain_id(monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(random_domain()))
    with RosPublisher("/x", JointState) as pub:
        assert pub.domain_id == int(os.environ["ROS_DOMAIN_ID"])


def test_invalid_qos_and_type_are_rejected():
    with pytest.raises(RosConfigError, match="QoS"):
        RosPublisher("/x", JointState, qos="fast", domain_id=1)
    with pytest.raises(RosConfigError, match="geometry_msgs/msg/Twist"):
        RosPublisher("/x", "geometry_msgs/msg/Twist", domain_id=1)
    with pytest.raises(RosConfigError, match="backend"):
        RosPublisher("/x", JointState, domain_id=1, backend="zenoh")
    with pytest.raises(RosConfigError, match="depth"):
        RosSubscriber("/x", JointState, domain_id=1, depth=0)


def test_history_depth_bounds_what_an_idle_subscriber_keeps():
    domain = random_domain()
    with (
        RosSubscriber("/d", JointState, qos="reliable", depth=3, domain_id=domain) as sub,
        RosPublisher("/d", JointState, qos="reliable", depth=50, domain_id=domain) as pub,
    ):
        assert sub.depth == 3 and pub.depth == 50
        assert pub.wait_for_subscribers(1, DISCOVERY_TIMEOUT_S) and sub.wait_for_publishers(1, DISCOVERY_TIMEOUT_S)
        for k in range(8):
            pub.publish(joint_state(["a"], [k], 0))
        deadline = time.monotonic() + DISCOVERY_TIMEOUT_S
        got = []
        while time.monotonic() < deadline and (not got or got[-1] != 7.0):
            time.sleep(0.05)  # let all 8 arrive before taking: only the newest 3 remain
            got += [m.position[0] for m in sub.take()]
        assert got == [5.0, 6.0, 7.0]
