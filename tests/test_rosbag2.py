"""A run directory is a ROS 2 bag: rosbags opens it and reads the values of signals.csv."""

from __future__ import annotations

import csv
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("mcap_ros2", reason="run.mcap needs the mcap packages (rtloop[ros])")
pytest.importorskip("rosbags", reason="reading bags needs rosbags")
pytest.importorskip("ruamel.yaml", reason="parsing metadata.yaml needs a YAML library (rosbags uses ruamel)")

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

import rtloop
from rt_test_runnables import Counter, Integrator, RaiseFrom
from rtloop import App, TaskFailed
from rtloop.record.rosbag2 import (
    METADATA_FILE,
    BagContents,
    BagTopic,
    offered_qos_profiles,
    render_metadata,
)
from rtloop.ros import dds

P = 1_000_000
SIGNALS = "/rtloop/signals"


def small_app(name: str, policy: str = "fifo") -> App:
    """Two tasks at different periods, so the timing topics differ in message count."""
    app = App(f"{name}_{os.getpid()}")
    counter = app.add_task("counter", Counter(), period_ns=P, policy=policy)
    integrator = app.add_task("integrator", Integrator(n=2), period_ns=2 * P, policy=policy)
    app.connect(counter.y[0:2], integrator.u[0:2])
    app.record(counter.y, integrator.y)
    return app


def read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    with open(path, newline="") as file:
        rows = list(csv.reader(file))
    return rows[0], rows[1:]


def timing_rows(run_dir: Path, task: str) -> list[tuple[int, ...]]:
    _, rows = read_csv(run_dir / "timing.csv")
    return [tuple(int(x) for x in row[1:]) for row in rows if row[0] == task]


def load_yaml(text: str):
    return YAML(typ="safe", pure=True).load(text)


def read_bag(run_dir: Path, typestore=None) -> dict[str, list]:
    """Every message of the bag decoded by rosbags, per topic, with its log time."""
    by_topic: dict[str, list] = {}
    with AnyReader([run_dir], default_typestore=typestore) as reader:
        assert reader.is2
        by_topic["__types__"] = {c.topic: c.msgtype for c in reader.connections}
        by_topic["__counts__"] = {c.topic: c.msgcount for c in reader.connections}
        for connection, timestamp, raw in reader.messages():
            by_topic.setdefault(connection.topic, []).append(
                (timestamp, reader.deserialize(raw, connection.msgtype), raw))
    return by_topic


def assert_bag_equals_csv_files(run_dir: Path, typestore=None) -> dict[str, list]:
    bag = read_bag(run_dir, typestore)
    header, rows = read_csv(run_dir / "signals.csv")
    assert bag["__types__"] == {
        SIGNALS: "sensor_msgs/msg/JointState",
        "/rtloop/timing/counter": "rtloop_msgs/msg/CycleTiming",
        "/rtloop/timing/integrator": "rtloop_msgs/msg/CycleTiming",
    }
    signals = bag[SIGNALS]
    assert bag["__counts__"][SIGNALS] == len(signals) == len(rows) > 0
    t0_log_ns = signals[0][0]
    for (log_ns, message, _), row in zip(signals, rows, strict=True):
        assert list(message.name) == header[1:]
        assert [repr(float(v)) for v in message.position] == row[1:]  # bit for bit
        assert (log_ns - t0_log_ns) / 1e9 == pytest.approx(float(row[0]), abs=1e-12)
    for task in ("counter", "integrator"):
        topic = f"/rtloop/timing/{task}"
        expected = timing_rows(run_dir, task)
        got = [(m.cycle, m.release_ns, m.start_ns, m.end_ns) for _, m, _ in bag[topic]]
        assert bag["__counts__"][topic] == len(got) == len(expected) > 0
        assert got == expected
    return bag


def test_simulated_run_directory_reads_as_a_bag_equal_to_the_csv_files(tmp_path: Path) -> None:
    rtloop.simulate(small_app("rosbag_sim"), 0.2, tmp_path)
    bag = assert_bag_equals_csv_files(tmp_path)
    assert bag["__counts__"]["/rtloop/timing/counter"] == 2 * bag["__counts__"]["/rtloop/timing/integrator"]
    metadata = load_yaml((tmp_path / METADATA_FILE).read_text())["rosbag2_bagfile_information"]
    log_times = [t for topic, messages in bag.items() if topic.startswith("/") for t, _, _ in messages]
    assert metadata["starting_time"]["nanoseconds_since_epoch"] == min(log_times)
    assert metadata["duration"]["nanoseconds"] == max(log_times) - min(log_times)
    assert metadata["message_count"] == len(log_times)
    with AnyReader([tmp_path]) as reader:  # rosbags' start/end come from metadata.yaml
        assert (reader.start_time, reader.end_time) == (min(log_times), max(log_times) + 1)


@pytest.mark.parametrize("store", [Stores.ROS2_HUMBLE, Stores.ROS2_JAZZY])
def test_humble_and_jazzy_type_stores_decode_the_bag(tmp_path: Path, store: Stores) -> None:
    """Read with each distro's type store, and decode the JointState bytes with that
    distro's own definition (not the one embedded in run.mcap)."""
    rtloop.simulate(small_app(f"rosbag_{store.value}"), 0.1, tmp_path)
    typestore = get_typestore(store)
    bag = assert_bag_equals_csv_files(tmp_path, typestore)
    _, rows = read_csv(tmp_path / "signals.csv")
    for (log_ns, _, raw), row in zip(bag[SIGNALS], rows, strict=True):
        message = typestore.deserialize_cdr(raw, "sensor_msgs/msg/JointState")
        assert [repr(float(v)) for v in message.position] == row[1:]
        assert message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec == log_ns


def test_metadata_has_every_key_humble_and_jazzy_require_and_matches_the_mcap(tmp_path: Path) -> None:
    rtloop.simulate(small_app("rosbag_keys"), 0.05, tmp_path)
    metadata = load_yaml((tmp_path / METADATA_FILE).read_text())["rosbag2_bagfile_information"]
    assert metadata["version"] == 8 and metadata["storage_identifier"] == "mcap"
    assert metadata["relative_file_paths"] == ["run.mcap"]
    assert (metadata["compression_format"], metadata["compression_mode"]) == ("", "")
    assert metadata["custom_data"] == {} and metadata["ros_distro"] == ""
    [file_info] = metadata["files"]
    assert file_info == {"path": "run.mcap", "starting_time": metadata["starting_time"],
                         "duration": metadata["duration"], "message_count": metadata["message_count"]}
    with open(tmp_path / "run.mcap", "rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
    channels = {c.topic: c for c in summary.channels.values()}
    counts = summary.statistics.channel_message_counts
    topics = metadata["topics_with_message_count"]
    assert [t["topic_metadata"]["name"] for t in topics] == list(channels)
    for topic in topics:
        described = topic["topic_metadata"]
        channel = channels[described["name"]]
        schema = summary.schemas[channel.schema_id]
        assert (schema.name, schema.encoding, channel.message_encoding) == (described["type"], "ros2msg", "cdr")
        assert described["serialization_format"] == "cdr" and described["type_description_hash"] == ""
        # Humble reads the QoS only as a string; it is the one in the channel metadata.
        assert isinstance(described["offered_qos_profiles"], str)
        assert described["offered_qos_profiles"] == channel.metadata["offered_qos_profiles"]
        assert topic["message_count"] == counts[channel.id]
    assert metadata["message_count"] == sum(counts.values())


def test_offered_qos_is_reliable_keep_last_like_the_reliable_preset() -> None:
    [profile] = load_yaml(offered_qos_profiles())
    assert profile["history"] == 1 and profile["reliability"] == 1 and profile["durability"] == 2
    assert profile["depth"] == dds._HISTORY_DEPTH["reliable"]
    assert profile["deadline"] == profile["lifespan"] == {"sec": 0, "nsec": 0}
    assert profile["avoid_ros_namespace_conventions"] is False


def test_strings_are_quoted_so_yaml_reads_them_back_unchanged() -> None:
    odd = BagTopic('/a"b\\c: #d', "yes", 3, "- x: 1\n  y: 'z'\n")
    text = render_metadata(BagContents("null", (odd,), 5, 7))
    metadata = load_yaml(text)["rosbag2_bagfile_information"]
    [topic] = metadata["topics_with_message_count"]
    assert topic["topic_metadata"]["name"] == odd.name
    assert topic["topic_metadata"]["type"] == "yes"  # not the YAML 1.1 boolean
    assert topic["topic_metadata"]["offered_qos_profiles"] == odd.offered_qos_profiles
    assert metadata["relative_file_paths"] == ["null"] and metadata["message_count"] == 3
    empty = load_yaml(render_metadata(BagContents("run.mcap", (), 0, 0)))
    assert empty["rosbag2_bagfile_information"]["topics_with_message_count"] == []
    with pytest.raises(ValueError, match="duration_ns=-1"):
        render_metadata(BagContents("run.mcap", (), 5, -1))


@pytest.mark.parametrize("how", ["simulate", "run"])
def test_a_run_that_ends_by_a_fault_is_still_a_bag(tmp_path: Path, how: str) -> None:
    app = App(f"rosbag_fault_{how}_{os.getpid()}")
    bad = app.add_task("bad", RaiseFrom(cycle=37), period_ns=P, policy="other")
    app.record(bad.y)
    with pytest.raises(TaskFailed) as failed:
        (rtloop.simulate if how == "simulate" else rtloop.run)(app, 5, tmp_path)
    _, rows = read_csv(tmp_path / "signals.csv")
    timing = timing_rows(tmp_path, "bad")
    bag = read_bag(tmp_path)
    assert bag["__counts__"] == {SIGNALS: len(rows), "/rtloop/timing/bad": len(timing)}
    assert [m.position[0] for _, m, _ in bag[SIGNALS]] == [float(r[1]) for r in rows]
    assert [m.cycle for _, m, _ in bag["/rtloop/timing/bad"]] == [t[0] for t in timing]
    # The last step that finished is the last row of both (36, unless a loaded machine skipped it).
    assert timing[-1][0] == bag[SIGNALS][-1][1].position[0] < failed.value.cycle
    assert failed.value.cycle >= 37 and (how == "run" or timing[-1][0] == 36)


KILLED_RUN = """
import sys
import rtloop
from rt_test_runnables import Counter
from rtloop import App
app = App(sys.argv[2])
app.record(app.add_task("counter", Counter(), period_ns=1_000_000).y)
rtloop.simulate(app, 3600, sys.argv[1])
"""


def test_a_killed_run_leaves_no_metadata_and_a_footerless_mcap(tmp_path: Path, rtloop_env) -> None:
    """What a SIGKILLed run leaves: run.mcap without its footer (only the chunks written
    before the kill) and no metadata.yaml, which is written when the run closes.
    rosbags rejects such a file; the complete chunks are still readable record by record."""
    process = subprocess.Popen([sys.executable, "-c", KILLED_RUN, str(tmp_path), f"rosbag_kill_{os.getpid()}"],
                               env=rtloop_env)
    try:
        deadline = time.monotonic() + 120
        mcap_path = tmp_path / "run.mcap"
        while not (mcap_path.exists() and mcap_path.stat().st_size > 200_000):
            assert process.poll() is None, "the simulation ended before it could be killed"
            assert time.monotonic() < deadline, "run.mcap did not grow"
            time.sleep(0.05)
    finally:
        os.kill(process.pid, signal.SIGKILL)
        process.wait()
    assert not (tmp_path / METADATA_FILE).exists()
    with pytest.raises(AnyReaderError, match="magic"):
        AnyReader([mcap_path]).open()
    messages = 0
    with open(mcap_path, "rb") as stream:
        try:
            for record in StreamReader(stream).records:
                messages += isinstance(record, Message)
        except (McapError, struct.error):  # the record the kill cut short
            pass
    assert messages > 1000
