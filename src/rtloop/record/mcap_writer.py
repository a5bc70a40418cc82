"""``run.mcap``: a run's signals and timing as ROS 2 messages (ros2msg schemas, CDR).

Opens in Foxglove and PlotJuggler and reads with ``ros2 bag`` and ``mcap_ros2``.

Topics:

``/rtloop/signals`` — ``sensor_msgs/msg/JointState``, one message per tick, with
    ``name`` = the recorded signal names (``plant.y[0]``) and ``position`` = their
    values; ``header.stamp`` and the log time are the tick's release time on the wall
    clock. Why JointState and not ``Float64MultiArray``: the names travel with the
    values, so ``ros2 bag``/Foxglove show what each number is, and PlotJuggler and
    Rerun have a JointState parser that makes one series per name
    (``/rtloop/signals/plant.y[0]/position``). One message per tick (not one per
    signal) keeps a tick atomic and the file small; ``per_signal_topics=True`` adds
    a ``std_msgs/msg/Float64`` topic per signal for tools that plot by topic.
``/rtloop/timing/<task>`` — ``rtloop_msgs/msg/CycleTiming``, one per cycle: cycle,
    release/start/end (``CLOCK_MONOTONIC`` ns, as ``timing.csv``), latency and
    execution time. The schema is embedded in the file, so no package is needed to
    read it.

Written incrementally (:class:`RunMcapWriter`), because the supervisor writes as it
drains; :func:`write_run_mcap` writes a finished run in one call.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from os import PathLike
from typing import Any

import numpy as np

SIGNALS_TOPIC = "/rtloop/signals"
TIMING_TOPIC_PREFIX = "/rtloop/timing/"
SIGNAL_TOPIC_PREFIX = "/rtloop/signal/"
NS_PER_S = 1_000_000_000

_SEPARATOR = "\n" + "=" * 80 + "\n"
_TIME_MSG = "int32 sec\nuint32 nanosec\n"
_HEADER_MSG = "builtin_interfaces/Time stamp\nstring frame_id\n"
JOINT_STATE_SCHEMA = (
    "std_msgs/Header header\n"
    "string[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n"
    + _SEPARATOR + "MSG: std_msgs/Header\n" + _HEADER_MSG
    + _SEPARATOR + "MSG: builtin_interfaces/Time\n" + _TIME_MSG
)
FLOAT64_SCHEMA = "float64 data\n"
CYCLE_TIMING_SCHEMA = (
    "# One cycle of an rtloop task; times are CLOCK_MONOTONIC nanoseconds (timing.csv).\n"
    "uint64 cycle\n"
    "int64 release_ns\n"
    "int64 start_ns\n"
    "int64 end_ns\n"
    "# start_ns - release_ns: wake-up latency, as cyclictest measures it\n"
    "int64 latency_ns\n"
    "# end_ns - start_ns: time spent reading inputs, stepping and publishing\n"
    "int64 exec_ns\n"
)


def topic_token(name: str) -> str:
    """Turn a task or signal name into a ROS 2 topic token: ``plant.y[0]`` → ``plant_y_0``."""
    token = re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", name)).strip("_")
    return token if token and not token[0].isdigit() else f"n_{token}"


def _stamp(wall_ns: int) -> dict[str, int]:
    sec, nanosec = divmod(wall_ns, NS_PER_S)
    return {"sec": sec, "nanosec": nanosec}


class RunMcapWriter:
    """Writes ``run.mcap`` while a run is in progress.

    Args:
        path: file to create (or a binary stream).
        signal_names: names of the recorded signals, in column order.
        t0_ns: the run's epoch T0 on ``CLOCK_MONOTONIC`` (timing records use this
            clock; signal rows use time since T0).
        wall_t0_ns: T0 on the wall clock (``time.time_ns()`` at T0), used for log
            times and stamps so tools show when the run happened.
        per_signal_topics: also write one ``std_msgs/msg/Float64`` topic per signal.
        metadata: extra ``key: value`` strings stored in the ``rtloop`` metadata record.

    Use as a context manager or call :meth:`close`; the file is complete (indexed)
    only after that.
    """

    def __init__(
        self,
        path: str | PathLike[str] | Any,
        signal_names: Sequence[str],
        t0_ns: int,
        wall_t0_ns: int,
        per_signal_topics: bool = False,
        metadata: Mapping[str, str] | None = None,
    ) -> None:
        from mcap.writer import CompressionType
        from mcap_ros2.writer import Writer

        self.signal_names = [str(name) for name in signal_names]
        self.t0_ns = int(t0_ns)
        self.wall_t0_ns = int(wall_t0_ns)
        self.per_signal_topics = per_signal_topics
        self.signal_topics = self._signal_topics() if per_signal_topics else []
        self.messages_written = 0
        """Messages written so far, all topics together."""
        # Open the file ourselves: mcap's writer takes only str paths and we close it.
        self._file = open(path, "wb") if isinstance(path, str | PathLike) else None  # noqa: SIM115
        self._writer = Writer(self._file or path, compression=CompressionType.ZSTD)
        self._joint_state = self._writer.register_msgdef("sensor_msgs/msg/JointState",
                                                         JOINT_STATE_SCHEMA)
        self._timing = self._writer.register_msgdef("rtloop_msgs/msg/CycleTiming",
                                                    CYCLE_TIMING_SCHEMA)
        self._float64 = (self._writer.register_msgdef("std_msgs/msg/Float64", FLOAT64_SCHEMA)
                         if per_signal_topics else None)
        self._sequence: dict[str, int] = {}
        self._closed = False
        info = {"t0_ns": str(self.t0_ns), "wall_t0_ns": str(self.wall_t0_ns),
                "signals": ",".join(self.signal_names)}
        self._writer.add_metadata("rtloop", {**info, **dict(metadata or {})})

    def _signal_topics(self) -> list[str]:
        topics = [SIGNAL_TOPIC_PREFIX + topic_token(name) for name in self.signal_names]
        if len(set(topics)) != len(topics):
            clashes = sorted({t for t in topics if topics.count(t) > 1})
            raise ValueError(f"signal names map to the same topic: {clashes}; "
                             "rename them or use per_signal_topics=False")
        return topics

    def _next_sequence(self, topic: str) -> int:
        sequence = self._sequence.get(topic, 0)
        self._sequence[topic] = sequence + 1
        return sequence

    def add_rows(self, t_ns: np.ndarray | Sequence[int], values: np.ndarray) -> None:
        """Add recorded signal rows.

        Args:
            t_ns: integer nanoseconds since T0 of each row (tick k of period P: k·P).
            values: shape ``(len(t_ns), len(signal_names))``; NaN where a signal has no
                value yet.
        """
        times = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        rows = np.asarray(values, dtype=np.float64).reshape(len(times), len(self.signal_names))
        names = self.signal_names
        for t, row in zip(times.tolist(), rows.tolist(), strict=True):
            wall_ns = self.wall_t0_ns + t
            message = {"header": {"stamp": _stamp(wall_ns), "frame_id": ""}, "name": names,
                       "position": row, "velocity": [], "effort": []}
            self._writer.write_message(SIGNALS_TOPIC, self._joint_state, message,
                                       log_time=wall_ns,
                                       sequence=self._next_sequence(SIGNALS_TOPIC))
            self.messages_written += 1
            for topic, value in zip(self.signal_topics, row, strict=False):
                self._writer.write_message(topic, self._float64, {"data": value},
                                           log_time=wall_ns,
                                           sequence=self._next_sequence(topic))
                self.messages_written += 1

    def add_timing(self, task: str, records: np.ndarray) -> None:
        """Add timing records of ``task``: rows ``(cycle, release_ns, start_ns, end_ns)``.

        The times are ``CLOCK_MONOTONIC`` ns as the task measured them (the same clock
        as ``t0_ns``); the log time is the release time on the wall clock.
        """
        topic = TIMING_TOPIC_PREFIX + topic_token(task)
        table = np.asarray(records, dtype=np.int64).reshape(-1, 4)
        offset = self.wall_t0_ns - self.t0_ns
        for cycle, release, start, end in table.tolist():
            message = {"cycle": cycle, "release_ns": release, "start_ns": start,
                       "end_ns": end, "latency_ns": start - release, "exec_ns": end - start}
            self._writer.write_message(topic, self._timing, message,
                                       log_time=release + offset,
                                       sequence=self._next_sequence(topic))
            self.messages_written += 1

    def close(self) -> None:
        """Write the index and summary; the file is complete after this. Safe twice."""
        if not self._closed:
            self._closed = True
            try:
                self._writer.finish()
            finally:  # a full disk makes finish() fail: the file is closed all the same
                if self._file is not None:
                    self._file.close()

    def __enter__(self) -> RunMcapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_run_mcap(
    path: str | PathLike[str],
    signal_names: Sequence[str],
    t_ns: np.ndarray,
    values: np.ndarray,
    timing: Mapping[str, np.ndarray],
    t0_ns: int,
    wall_t0_ns: int,
    per_signal_topics: bool = False,
) -> int:
    """Write a finished run to ``path`` in one call; return the number of messages.

    Args:
        path: the ``run.mcap`` to create.
        signal_names: recorded signal names, one per column of ``values``.
        t_ns: nanoseconds since T0 of each signal row.
        values: recorded values, shape ``(len(t_ns), len(signal_names))``.
        timing: per task, rows ``(cycle, release_ns, start_ns, end_ns)``.
        t0_ns, wall_t0_ns, per_signal_topics: as for :class:`RunMcapWriter`.
    """
    with RunMcapWriter(path, signal_names, t0_ns, wall_t0_ns,
                       per_signal_topics=per_signal_topics) as writer:
        writer.add_rows(t_ns, values)
        for task, records in timing.items():
            writer.add_timing(task, records)
    return writer.messages_written


def merge_mcap_files(sources: Sequence[str | PathLike[str]], target: str | PathLike[str]) -> int:
    """Write the messages of several ``RunMcapWriter`` files into one, in order; return their count.

    The messages are copied as they are (no decoding); schemas and channels are matched by
    name and topic, the ``rtloop`` metadata is taken from the first file.
    """
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    count = 0
    with open(target, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        schemas: dict[str, int] = {}
        channels: dict[str, int] = {}
        for number, source in enumerate(sources):
            with open(source, "rb") as file:
                reader = make_reader(file)
                if number == 0:
                    writer.start(profile=reader.get_header().profile, library=reader.get_header().library)
                    for record in reader.iter_metadata():
                        writer.add_metadata(record.name, dict(record.metadata))
                for schema, channel, message in reader.iter_messages(log_time_order=False):
                    if channel.topic not in channels:
                        if schema is None:
                            raise ValueError(f"{source}: channel {channel.topic!r} has no schema")
                        if schema.name not in schemas:
                            schemas[schema.name] = writer.register_schema(schema.name, schema.encoding, schema.data)
                        channels[channel.topic] = writer.register_channel(
                            channel.topic, channel.message_encoding, schemas[schema.name], dict(channel.metadata))
                    writer.add_message(channels[channel.topic], message.log_time, message.data,
                                       message.publish_time, message.sequence)
                    count += 1
        if not sources:
            writer.start(profile="ros2")
        writer.finish()
    return count
