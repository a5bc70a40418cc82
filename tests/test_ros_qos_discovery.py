"""QoS and discovery as a ROS 2 node sees them.

- rtloop publishes *reliable, keep last* by default, so a reader with ROS 2's default QoS
  (reliable, volatile, keep last 10: rclpy, ``ros2 topic echo``) receives; the best-effort
  ``sensor`` preset stays available and such a reader gets nothing from it.
- ``ROS_AUTOMATIC_DISCOVERY_RANGE`` / ``ROS_LOCALHOST_ONLY`` / ``ROS_STATIC_PEERS`` become
  the Cyclone DDS configuration rmw_cyclonedds would generate, before ``CYCLONEDDS_URI``.

Peers run in their own processes with their own environment and a private random domain.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from ros2_peer_types import ROS2_TYPES

pytest.importorskip("cyclonedds")

from rtloop.app.appfile import load_app
from rtloop.app.builder import App
from rtloop.ros.discovery import Discovery, cyclone_config, cyclone_config_string, discovery_from_env
from test_ros_app import random_domain

SRC = Path(__file__).resolve().parents[1] / "src"

# Someone else's ROS 2 node: plain cyclonedds, ROS 2 default QoS unless told "best_effort".
READER = textwrap.dedent(
    """
    import sys, time
    from cyclonedds.core import ReadCondition, SampleState, WaitSet
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration
    """
) + ROS2_TYPES + textwrap.dedent(
    """
    domain, topic, reliability, wait_s = int(sys.argv[1]), sys.argv[2], sys.argv[3], float(sys.argv[4])
    participant = DomainParticipant(domain)
    policy = (Policy.Reliability.Reliable(duration(milliseconds=100)) if reliability == "reliable"
              else Policy.Reliability.BestEffort)
    qos = Qos(policy, Policy.Durability.Volatile, Policy.History.KeepLast(10))
    reader = DataReader(participant, Topic(participant, topic, JointState_), qos=qos)
    waitset = WaitSet(participant)
    waitset.attach(ReadCondition(reader, SampleState.NotRead))
    print("READY", flush=True)
    got, deadline = 0, time.monotonic() + wait_s
    while time.monotonic() < deadline and got < 20:
        waitset.wait(duration(milliseconds=100))
        got += sum(1 for s in reader.take(N=100) if hasattr(s, "header"))
    print(got, flush=True)
    """
)

# rtloop's own publisher in a process of its own, so it reads the environment it is given.
PUBLISHER = textwrap.dedent(
    """
    import sys, time
    from rtloop.ros.dds import RosPublisher
    from rtloop.ros.messages import joint_state
    domain, topic, qos, seconds = int(sys.argv[1]), sys.argv[2], sys.argv[3], float(sys.argv[4])
    with RosPublisher(topic, "sensor_msgs/msg/JointState", qos=qos, domain_id=domain) as pub:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            pub.publish(joint_state(["a"], [1.0], time.time_ns()))
            time.sleep(0.02)
    """
)


def received_count(qos: str, reader_reliability: str, *, publisher_env: dict[str, str] | None = None,
                   reader_env: dict[str, str] | None = None, wait_s: float = 60.0) -> int:
    """How many messages a peer reader got from an rtloop publisher (both in their own processes).

    The reader stops at 20 messages, so ``wait_s`` bounds a publisher that reaches it: it starts once
    the reader is ready and imports DDS first: seconds on a loaded machine, where a case that passed
    took 9 s at a load average of ~7, close to the 8 s the reader waited before. The silent cases pass
    a short ``wait_s``: they wait all of it."""
    domain, topic = random_domain(), "rt/qos_test/angles"
    base = {**os.environ, "PYTHONPATH": str(SRC)}
    for name in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS", "CYCLONEDDS_URI"):
        base.pop(name, None)
    reader = subprocess.Popen([sys.executable, "-c", READER, str(domain), topic, reader_reliability, str(wait_s)],
                              env={**base, **(reader_env or {})}, stdout=subprocess.PIPE, text=True)
    try:
        assert reader.stdout is not None and reader.stdout.readline().strip() == "READY"
        publisher = subprocess.Popen([sys.executable, "-c", PUBLISHER, str(domain), "/qos_test/angles", qos,
                                      str(wait_s)], env={**base, **(publisher_env or {})})
        out, _ = reader.communicate(timeout=wait_s + 30)
        publisher.kill()
        publisher.wait(timeout=10)
    finally:
        if reader.poll() is None:
            reader.kill()
            reader.wait()
    return int(out.strip())


# --- QoS -------------------------------------------------------------------------------------------


def test_default_publisher_reaches_a_reader_with_ros2_default_qos() -> None:
    assert received_count("reliable", "reliable") > 0


def test_sensor_preset_still_exists_and_only_best_effort_readers_get_it() -> None:
    assert received_count("sensor", "best_effort") > 0
    assert received_count("sensor", "reliable", wait_s=3.0) == 0  # incompatible QoS: silence, as in ROS 2


def test_app_publishes_reliable_unless_told_otherwise(tmp_path: Path) -> None:
    from rt_test_runnables import Counter  # a module-level runnable the test suite shares

    app = App("qos_default")
    task = app.add_task("t", Counter(), period_ns=1_000_000)
    assert app.ros_publish("/a", source=task.y[0:1]).qos == "reliable"
    assert app.ros_publish("/b", source=task.y[0:1], qos="sensor").qos == "sensor"
    app_file = tmp_path / "app.toml"
    app_file.write_text(textwrap.dedent("""
        name = "qos_file"
        [tasks.t]
        runnable = "rt_test_runnables:Counter"
        period_ns = 1_000_000
        [[ros.publish]]
        topic = "/a"
        source = "t.y[0:1]"
    """))
    assert [t.qos for t in load_app(app_file).ros_topics] == ["reliable"]


# --- discovery -------------------------------------------------------------------------------------


def test_discovery_is_read_like_rcl() -> None:
    assert discovery_from_env({}) == Discovery("SUBNET")
    assert discovery_from_env({"ROS_AUTOMATIC_DISCOVERY_RANGE": "localhost"}).range == "LOCALHOST"
    assert discovery_from_env({"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF", "ROS_STATIC_PEERS": "10.0.0.2"}) \
        == Discovery("OFF")  # static peers are ignored when discovery is off
    assert discovery_from_env({"ROS_STATIC_PEERS": "10.0.0.2; robot.local;"}).static_peers == ("10.0.0.2",
                                                                                              "robot.local")
    # Humble's switch wins and drops the static peers
    assert discovery_from_env({"ROS_LOCALHOST_ONLY": "1", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
                               "ROS_STATIC_PEERS": "10.0.0.2"}) == Discovery("LOCALHOST")
    odd = discovery_from_env({"ROS_AUTOMATIC_DISCOVERY_RANGE": "everywhere"})
    assert odd.range == "LOCALHOST" and "everywhere" in odd.warning


def test_cyclone_config_matches_what_rmw_cyclonedds_generates() -> None:
    assert cyclone_config(Discovery("SUBNET")) == ""
    assert cyclone_config(Discovery("SYSTEM_DEFAULT", ("x",))) == ""
    local = cyclone_config(Discovery("LOCALHOST", ("10.0.0.2",)))
    assert "<AllowMulticast>false</AllowMulticast>" in local
    assert '<Peer address="localhost"/><Peer address="10.0.0.2"/>' in local
    assert "<MaxAutoParticipantIndex>32</MaxAutoParticipantIndex>" in local
    off = cyclone_config(Discovery("OFF"), pid=1234)
    assert "<Tag>ros_discovery_off_1234</Tag>" in off and "<ParticipantIndex>none</ParticipantIndex>" in off
    assert '<Peers><Peer address="10.0.0.2"/></Peers>' in cyclone_config(Discovery("SUBNET", ("10.0.0.2",)))
    # the user's own configuration comes last, so it has the last word
    text = cyclone_config_string({"ROS_LOCALHOST_ONLY": "1", "CYCLONEDDS_URI": "file:///etc/cyclone.xml"})
    assert text is not None and text.endswith(",file:///etc/cyclone.xml") and text.startswith("<CycloneDDS>")
    assert cyclone_config_string({}) is None


@pytest.mark.parametrize("variables", [{"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}, {"ROS_LOCALHOST_ONLY": "1"}])
def test_localhost_range_still_finds_this_host(variables: dict[str, str]) -> None:
    # The peer is plain cyclonedds: as a ROS 2 node on rmw_cyclonedds would, it runs with the
    # LOCALHOST configuration (multicast off, unicast to this host's participant indices).
    peer = {"CYCLONEDDS_URI": cyclone_config(Discovery("LOCALHOST"))}
    assert received_count("reliable", "reliable", publisher_env=variables, reader_env=peer) > 0


def test_discovery_off_finds_no_other_process() -> None:
    off = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    assert received_count("reliable", "reliable", publisher_env=off, reader_env=off, wait_s=3.0) == 0


def test_cyclonedds_uri_is_still_honoured(tmp_path: Path) -> None:
    # A user's file that turns multicast off and names no peer: the two never meet.
    config = tmp_path / "cyclone.xml"
    config.write_text('<CycloneDDS><Domain id="any"><General><AllowMulticast>false</AllowMulticast></General>'
                      '<Discovery><ParticipantIndex>none</ParticipantIndex></Discovery></Domain></CycloneDDS>')
    uri = {"CYCLONEDDS_URI": f"file://{config}"}
    assert received_count("reliable", "reliable", publisher_env=uri, wait_s=3.0) == 0
