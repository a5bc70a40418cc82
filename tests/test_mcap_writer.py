"""run.mcap: ROS 2 messages (ros2msg schemas, CDR) that read back bit-for-bit."""

from __future__ import annotations

import io
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("mcap_ros2")

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from rtloop.record.mcap_writer import RunMcapWriter, topic_token, write_run_mcap

T0_NS = 7_000_000_000  # CLOCK_MONOTONIC at T0
WALL_T0_NS = 1_763_000_000_123_456_789  # time.time_ns() at T0
NAMES = ["plant.y[0]", "plant.y[1]", "controller.u[0]"]


def make_run(n: int = 200, period_ns: int = 1_000_000, seed: int = 1):
    rng = np.random.default_rng(seed)
    t_ns = np.arange(n, dtype=np.int64) * period_ns
    values = rng.standard_normal((n, len(NAMES))) * 10.0 ** rng.integers(-300, 300, (n, 3))
    values[0] = [0.1 + 0.2, -0.0, 5e-324]  # inexact, negative zero, subnormal
    values[1, 2] = np.nan  # a slower task without a value yet
    release = T0_NS + t_ns
    start = release + rng.integers(1_000, 90_000, n)
    end = start + rng.integers(10_000, 50_000, n)
    records = np.stack([np.arange(n), release, start, end], axis=1).astype(np.int64)
    return t_ns, values, records


def read_ros2_messages(source, topics=None):
    """Decode with mcap's reader and mcap_ros2's decoder (read_ros2_messages' replacement:
    ``mcap_ros2.reader`` warns that it is deprecated)."""
    stream = open(source, "rb") if not hasattr(source, "read") else source  # noqa: SIM115
    with stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for schema, channel, message, ros_msg in reader.iter_decoded_messages(
                topics=topics, log_time_order=True):
            yield SimpleNamespace(schema=schema, channel=channel, message=message,
                                  ros_msg=ros_msg, log_time_ns=message.log_time)


def read_topic(path, topic):
    return list(read_ros2_messages(path, topics=[topic]))


def test_signals_read_back_bit_for_bit(tmp_path):
    t_ns, values, records = make_run()
    path = tmp_path / "run.mcap"
    count = write_run_mcap(path, NAMES, t_ns, values, {"controller": records}, T0_NS,
                           WALL_T0_NS)
    assert count == 2 * len(t_ns)
    messages = read_topic(path, "/rtloop/signals")
    assert len(messages) == len(t_ns)
    got = np.array([m.ros_msg.position for m in messages], dtype=np.float64)
    assert np.array_equal(got.view(np.uint64), values.view(np.uint64))  # NaN and -0.0 too
    for m, t in zip(messages, t_ns.tolist(), strict=True):
        assert m.schema.name == "sensor_msgs/msg/JointState"
        assert list(m.ros_msg.name) == NAMES
        assert m.log_time_ns == WALL_T0_NS + t
        stamp = m.ros_msg.header.stamp
        assert stamp.sec * 1_000_000_000 + stamp.nanosec == WALL_T0_NS + t


def test_timing_read_back_exactly(tmp_path):
    t_ns, values, records = make_run()
    path = tmp_path / "run.mcap"
    write_run_mcap(path, NAMES, t_ns, values, {"controller": records, "plant": records[:5]},
                   T0_NS, WALL_T0_NS)
    messages = read_topic(path, "/rtloop/timing/controller")
    assert [m.schema.name for m in messages[:1]] == ["rtloop_msgs/msg/CycleTiming"]
    got = np.array([[m.ros_msg.cycle, m.ros_msg.release_ns, m.ros_msg.start_ns,
                     m.ros_msg.end_ns] for m in messages], dtype=np.int64)
    assert np.array_equal(got, records)
    assert [m.ros_msg.latency_ns for m in messages] == (records[:, 2] - records[:, 1]).tolist()
    assert [m.ros_msg.exec_ns for m in messages] == (records[:, 3] - records[:, 2]).tolist()
    assert [m.log_time_ns for m in messages] == (records[:, 1] - T0_NS + WALL_T0_NS).tolist()
    assert len(read_topic(path, "/rtloop/timing/plant")) == 5


def test_file_follows_the_ros2_profile_and_stores_metadata(tmp_path):
    t_ns, values, records = make_run(10)
    path = tmp_path / "run.mcap"
    write_run_mcap(path, NAMES, t_ns, values, {"ctl": records}, T0_NS, WALL_T0_NS)
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert summary.statistics.message_count == 20
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert metadata["rtloop"]["t0_ns"] == str(T0_NS)
    assert metadata["rtloop"]["wall_t0_ns"] == str(WALL_T0_NS)
    assert metadata["rtloop"]["signals"] == ",".join(NAMES)


def test_joint_state_bytes_match_what_a_ros2_node_publishes(tmp_path):
    """The CDR in the file is what rtloop.ros publishes over DDS (independent encoders)."""
    ros_messages = pytest.importorskip("rtloop.ros.messages")
    if not ros_messages.HAVE_CYCLONEDDS:
        pytest.skip("cyclonedds is not installed")
    t_ns, values, _ = make_run(3)
    path = tmp_path / "run.mcap"
    write_run_mcap(path, NAMES, t_ns, values, {}, T0_NS, WALL_T0_NS)
    with open(path, "rb") as stream:
        raw = [message.data for _, _, message in make_reader(stream).iter_messages()]
    for data, t, row in zip(raw, t_ns.tolist(), values.tolist(), strict=True):
        expected = ros_messages.joint_state(NAMES, row, WALL_T0_NS + t).serialize()
        assert data == expected


def test_streaming_in_batches_equals_one_shot(tmp_path):
    t_ns, values, records = make_run(100)
    one_shot = tmp_path / "one.mcap"
    write_run_mcap(one_shot, NAMES, t_ns, values, {"c": records}, T0_NS, WALL_T0_NS)
    streamed = tmp_path / "streamed.mcap"
    with RunMcapWriter(streamed, NAMES, T0_NS, WALL_T0_NS) as writer:
        for lo in range(0, 100, 30):  # as the supervisor drains: uneven batches
            writer.add_rows(t_ns[lo:lo + 30], values[lo:lo + 30])
            writer.add_timing("c", records[lo:lo + 30])
        writer.add_rows(t_ns[:0], values[:0])
    def decoded(path):
        return [(m.channel.topic, m.log_time_ns, m.message.sequence, m.message.data)
                for m in read_ros2_messages(path)]
    assert decoded(streamed) == decoded(one_shot)


def test_per_signal_topics(tmp_path):
    t_ns, values, _ = make_run(20)
    buffer = io.BytesIO()
    with RunMcapWriter(buffer, NAMES, T0_NS, WALL_T0_NS, per_signal_topics=True) as writer:
        writer.add_rows(t_ns, values)
    buffer.seek(0)
    for column, name in enumerate(NAMES):
        topic = "/rtloop/signal/" + topic_token(name)
        messages = list(read_ros2_messages(io.BytesIO(buffer.getvalue()), topics=[topic]))
        got = np.array([m.ros_msg.data for m in messages])
        assert np.array_equal(got.view(np.uint64), values[:, column].view(np.uint64))
    assert topic_token("plant.y[0]") == "plant_y_0"
    assert topic_token("3d") == "n_3d"
    with pytest.raises(ValueError, match="same topic"):
        RunMcapWriter(io.BytesIO(), ["a.b", "a_b"], 0, 0, per_signal_topics=True)


def test_rows_must_match_the_signal_names(tmp_path):
    with RunMcapWriter(tmp_path / "x.mcap", NAMES, T0_NS, WALL_T0_NS) as writer, \
            pytest.raises(ValueError):
        writer.add_rows([0, 1], np.zeros((2, 2)))


def test_deprecated_mcap_ros2_reader_agrees(tmp_path):
    """The brief's reader, ``mcap_ros2.reader.read_ros2_messages``, still decodes it."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        from mcap_ros2.reader import read_ros2_messages as legacy_read

    t_ns, values, records = make_run(50)
    path = tmp_path / "run.mcap"
    write_run_mcap(path, NAMES, t_ns, values, {"c": records}, T0_NS, WALL_T0_NS)
    legacy = [m.ros_msg.position for m in legacy_read(str(path), topics=["/rtloop/signals"])]
    got = np.array(legacy, dtype=np.float64)
    assert np.array_equal(got.view(np.uint64), values.view(np.uint64))


def _segments(tmp_path, timing_tasks=("c", "d")):
    """Three files as the --keep window writes them: the same channels, consecutive rows."""
    t_ns, values, records = make_run(3000)
    paths = []
    for number, lo in enumerate(range(0, 3000, 1000)):
        path = tmp_path / f"{number:06d}-run.mcap"
        with RunMcapWriter(path, NAMES, T0_NS, WALL_T0_NS, timing_tasks=timing_tasks) as writer:
            for block in range(lo, lo + 1000, 300):  # uneven drain batches
                end = min(block + 300, lo + 1000)
                writer.add_rows(t_ns[block:end], values[block:end])
                writer.add_timing("c", records[block:end])
        paths.append(path)
    return paths, t_ns, values, records


def _all_messages(path):
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as stream:  # every record, its CRCs checked (chunks, data section, summary)
        assert sum(1 for _ in StreamReader(stream, validate_crcs=True).records) > 0
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        return reader.get_summary().statistics, [
            (channel.topic, message.log_time, message.publish_time, message.data)
            for _, channel, message in reader.iter_messages(log_time_order=True)]


def test_segments_are_joined_by_copying_chunks_and_read_as_if_merged_message_by_message(tmp_path):
    from rtloop.record.mcap_writer import _merge_messages, merge_mcap_files

    paths, t_ns, values, records = _segments(tmp_path)
    assert merge_mcap_files(paths, tmp_path / "joined.mcap") == 6000
    assert _merge_messages(paths, tmp_path / "merged.mcap") == 6000
    statistics, joined = _all_messages(tmp_path / "joined.mcap")
    _, merged = _all_messages(tmp_path / "merged.mcap")
    assert joined == merged
    assert statistics.message_count == 6000 and statistics.chunk_count >= 3
    assert statistics.message_start_time == WALL_T0_NS and statistics.message_end_time == WALL_T0_NS + t_ns[-1]
    got = np.array([m.ros_msg.position for m in read_topic(tmp_path / "joined.mcap", "/rtloop/signals")])
    assert np.array_equal(got.view(np.uint64), values.view(np.uint64))
    timing = read_topic(tmp_path / "joined.mcap", "/rtloop/timing/c")
    assert [m.ros_msg.cycle for m in timing] == records[:, 0].tolist()
    assert read_topic(tmp_path / "joined.mcap", "/rtloop/timing/d") == []  # declared, never written


def test_segments_with_different_channels_are_merged_message_by_message(tmp_path):
    from rtloop.record.mcap_writer import merge_mcap_files

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first = _segments(tmp_path / "a", ("c", "d"))[0][0]
    other = _segments(tmp_path / "b", ("d", "c"))[0][1]  # channel ids in another order
    assert merge_mcap_files([first, other], tmp_path / "joined.mcap") == 4000
    _, messages = _all_messages(tmp_path / "joined.mcap")
    assert len(messages) == 4000
    assert {topic for topic, *_ in messages} == {"/rtloop/signals", "/rtloop/timing/c"}
