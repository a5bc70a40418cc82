"""``metadata.yaml`` beside ``run.mcap``: a run directory is a ROS 2 bag.

With it, ``ros2 bag info RUN_DIR`` and ``ros2 bag play RUN_DIR`` (Humble and Jazzy) and
``rosbags`` open the run directory itself; without it ``ros2 bag`` refuses a directory
("Could not find metadata in bag directory") and opens only the bare ``run.mcap``.

Why version 8 with the QoS as a string: Humble (which writes version 5) reads
``offered_qos_profiles`` only as a string, and version 9 turns it into a YAML list;
Jazzy (which writes version 9) reads string QoS up to version 8. Neither rejects a
version higher than its own, so 8 is the newest both read. The keys added after
version 5 (``custom_data``, ``type_description_hash``, ``ros_distro``) are written
because Jazzy requires them at version 8; Humble ignores them.

The YAML is written here, not through a YAML library: its shape is fixed, every string
is emitted double-quoted with JSON escapes (valid YAML 1.1 and 1.2, so yaml-cpp, ruamel
and PyYAML read the same text), and the core keeps no YAML dependency.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

METADATA_FILE = "metadata.yaml"
METADATA_VERSION = 8
STORAGE_IDENTIFIER = "mcap"
SERIALIZATION_FORMAT = "cdr"

RELIABLE_HISTORY_DEPTH = 10
"""History depth of rtloop's ``reliable`` QoS preset (``ros/dds.py``), rclpy's default."""


def offered_qos_profiles(depth: int = RELIABLE_HISTORY_DEPTH) -> str:
    """The ``offered_qos_profiles`` string of a topic: reliable, keep last ``depth``, volatile.

    The form rosbag2 writes up to metadata version 8: a YAML list with one profile whose
    enums are RMW integers (KEEP_LAST=1, RELIABLE=1, VOLATILE=2, liveliness AUTOMATIC=1)
    and whose durations are ``{sec, nsec}``, zero meaning "unset". ``ros2 bag play``
    offers this QoS when it republishes, so reliable: a subscriber with rclpy's default
    (reliable) profile receives the messages, which best effort would not give it.
    """
    zero = "\n    sec: 0\n    nsec: 0\n"
    return (
        f"- history: 1\n  depth: {int(depth)}\n  reliability: 1\n  durability: 2\n"
        f"  deadline:{zero}  lifespan:{zero}"
        f"  liveliness: 1\n  liveliness_lease_duration:{zero}"
        "  avoid_ros_namespace_conventions: false\n"
    )


@dataclass(frozen=True)
class BagTopic:
    """One topic of the bag as ``metadata.yaml`` lists it."""

    name: str
    """ROS 2 topic name, such as ``/rtloop/signals``."""
    type_name: str
    """ROS 2 message type, such as ``sensor_msgs/msg/JointState``."""
    message_count: int
    """Messages written on this topic."""
    offered_qos_profiles: str
    """The QoS string also stored in the MCAP channel's metadata."""


@dataclass(frozen=True)
class BagContents:
    """What one storage file of the bag holds: the facts ``metadata.yaml`` states."""

    file_name: str
    """The storage file, relative to the bag directory (``run.mcap``)."""
    topics: tuple[BagTopic, ...]
    """Every topic with a channel in the file, in the order they were first written."""
    starting_time_ns: int
    """Earliest message log time, wall-clock ns since the epoch (0 when there is none)."""
    duration_ns: int
    """Latest minus earliest message log time (0 when there are fewer than two)."""

    @property
    def message_count(self) -> int:
        """Messages in the file, all topics together."""
        return sum(topic.message_count for topic in self.topics)


def _text(value: str) -> str:
    """A double-quoted YAML scalar (JSON's escapes are YAML's too)."""
    return json.dumps(value)


def _time_lines(indent: str, starting_time_ns: int, duration_ns: int) -> list[str]:
    return [
        f"{indent}starting_time:",
        f"{indent}  nanoseconds_since_epoch: {int(starting_time_ns)}",
        f"{indent}duration:",
        f"{indent}  nanoseconds: {int(duration_ns)}",
    ]


def render_metadata(contents: BagContents) -> str:
    """The text of ``metadata.yaml`` for a bag of one MCAP file."""
    if contents.starting_time_ns < 0 or contents.duration_ns < 0:
        raise ValueError(f"bag times must be >= 0 ns, got starting_time_ns="
                         f"{contents.starting_time_ns}, duration_ns={contents.duration_ns}")
    lines = [
        "rosbag2_bagfile_information:",
        f"  version: {METADATA_VERSION}",
        f"  storage_identifier: {STORAGE_IDENTIFIER}",
        *_time_lines("  ", contents.starting_time_ns, contents.duration_ns),
        f"  message_count: {contents.message_count}",
        "  topics_with_message_count:" + ("" if contents.topics else " []"),
    ]
    for topic in contents.topics:
        lines += [
            "    - topic_metadata:",
            f"        name: {_text(topic.name)}",
            f"        type: {_text(topic.type_name)}",
            f"        serialization_format: {SERIALIZATION_FORMAT}",
            f"        offered_qos_profiles: {_text(topic.offered_qos_profiles)}",
            '        type_description_hash: ""',
            f"      message_count: {int(topic.message_count)}",
        ]
    lines += [
        '  compression_format: ""',
        '  compression_mode: ""',
        "  relative_file_paths:",
        f"    - {_text(contents.file_name)}",
        "  files:",
        f"    - path: {_text(contents.file_name)}",
        *_time_lines("      ", contents.starting_time_ns, contents.duration_ns),
        f"      message_count: {contents.message_count}",
        "  custom_data: {}",
        '  ros_distro: ""',
    ]
    return "\n".join(lines) + "\n"


def write_metadata(bag_dir: Path, contents: BagContents) -> Path:
    """Write ``bag_dir/metadata.yaml`` atomically; return its path.

    Written to a temporary name in the same directory, flushed and synced, then renamed
    over the old file: a reader sees the previous metadata or the new, never half.
    """
    path = Path(bag_dir) / METADATA_FILE
    temporary = path.with_name(f".{METADATA_FILE}.{os.getpid()}.tmp")
    try:
        with open(temporary, "w", encoding="utf-8") as file:
            file.write(render_metadata(contents))
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path



def bag_contents_of(mcap_path: Path) -> BagContents:
    """What ``metadata.yaml`` says of an existing, complete run.mcap (from its summary section)."""
    from mcap.reader import make_reader

    with open(mcap_path, "rb") as file:
        summary = make_reader(file).get_summary()
    if summary is None or summary.statistics is None:
        raise OSError(f"{mcap_path.name} has no summary section")
    statistics = summary.statistics
    topics = []
    for channel_id, channel in sorted(summary.channels.items()):
        schema = summary.schemas.get(channel.schema_id)
        topics.append(BagTopic(channel.topic, schema.name if schema else "",
                               statistics.channel_message_counts.get(channel_id, 0),
                               channel.metadata.get("offered_qos_profiles", offered_qos_profiles())))
    first = statistics.message_start_time if statistics.message_count else 0
    last = statistics.message_end_time if statistics.message_count else 0
    return BagContents(mcap_path.name, tuple(topics), first, last - first)
