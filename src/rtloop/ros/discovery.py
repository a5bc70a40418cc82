"""Who a DDS participant may discover, read from ROS 2's environment, as rclpy does.

    ROS_AUTOMATIC_DISCOVERY_RANGE = SUBNET | LOCALHOST | OFF | SYSTEM_DEFAULT  (Iron and later)
    ROS_STATIC_PEERS              = "192.168.0.7;robot.local"                 (ignored when OFF)
    ROS_LOCALHOST_ONLY            = 1   (Humble's switch; forces LOCALHOST and drops static peers)

The range defaults to SUBNET; an unknown value means LOCALHOST, the cautious reading rcl
makes too. For the cyclonedds backend the range becomes a Cyclone DDS configuration, the
one rmw_cyclonedds generates, and ``CYCLONEDDS_URI`` (if set) is appended after it, so a
user's own file still has the last word. The rclpy backend needs none of this: rcl reads
the same variables.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

RANGES = ("SUBNET", "LOCALHOST", "OFF", "SYSTEM_DEFAULT")
# rmw_cyclonedds (Jazzy) caps the participant index at 32 for LOCALHOST: ~32 processes a host.
MAX_AUTO_PARTICIPANT_INDEX = 32


@dataclass(frozen=True)
class Discovery:
    """The discovery settings of this process's DDS participants."""

    range: str
    """SUBNET (multicast on the network), LOCALHOST (this host and static peers), OFF (this
    process only) or SYSTEM_DEFAULT (whatever the DDS configuration says)."""
    static_peers: tuple[str, ...] = ()
    """Hosts contacted by unicast besides multicast discovery (addresses or names)."""
    warning: str = ""
    """Why the environment was not taken as written ('' if it was)."""


def discovery_from_env(env: Mapping[str, str] | None = None) -> Discovery:
    """Read ``ROS_AUTOMATIC_DISCOVERY_RANGE``, ``ROS_STATIC_PEERS`` and ``ROS_LOCALHOST_ONLY``."""
    env = os.environ if env is None else env
    peers = tuple(p.strip() for p in env.get("ROS_STATIC_PEERS", "").split(";") if p.strip())
    if env.get("ROS_LOCALHOST_ONLY", "").strip() == "1":
        return Discovery("LOCALHOST")
    text = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").strip()
    if not text:
        return Discovery("SUBNET", peers)
    if text.upper() not in RANGES:
        return Discovery("LOCALHOST", peers, warning=f"ROS_AUTOMATIC_DISCOVERY_RANGE={text!r} is not one of "
                                                     f"{', '.join(RANGES)}; using LOCALHOST, as ROS 2 does")
    discovery_range = text.upper()
    return Discovery(discovery_range, () if discovery_range == "OFF" else peers)


def cyclone_config(discovery: Discovery, pid: int | None = None) -> str:
    """The Cyclone DDS XML for ``discovery`` ('' when Cyclone's own defaults do: SUBNET, no peers)."""
    peers = "".join(f'<Peer address="{_xml_attribute(peer)}"/>' for peer in discovery.static_peers)
    if discovery.range == "LOCALHOST":
        general = "<AllowMulticast>false</AllowMulticast>"
        found = (f"<ParticipantIndex>auto</ParticipantIndex>"
                 f"<MaxAutoParticipantIndex>{MAX_AUTO_PARTICIPANT_INDEX}</MaxAutoParticipantIndex>"
                 f'<Peers><Peer address="localhost"/>{peers}</Peers>')
    elif discovery.range == "OFF":
        # No multicast, no peers, and a tag no other process carries: nobody is found.
        general = "<AllowMulticast>false</AllowMulticast>"
        found = f"<ParticipantIndex>none</ParticipantIndex><Tag>ros_discovery_off_{pid or os.getpid()}</Tag>"
    elif discovery.range == "SUBNET" and peers:
        general, found = "", f"<Peers>{peers}</Peers>"
    else:
        return ""
    general = f"<General>{general}</General>" if general else ""
    return f'<CycloneDDS><Domain id="any">{general}<Discovery>{found}</Discovery></Domain></CycloneDDS>'


def cyclone_config_string(env: Mapping[str, str] | None = None) -> str | None:
    """What to give ``dds_create_domain``: our XML, then ``CYCLONEDDS_URI``; None for Cyclone's default."""
    env = os.environ if env is None else env
    parts = [cyclone_config(discovery_from_env(env)), env.get("CYCLONEDDS_URI", "").strip()]
    text = ",".join(part for part in parts if part)
    return text or None


def _xml_attribute(text: str) -> str:
    return text.replace("&", "&amp;").replace('"', "&quot;").replace("<", "&lt;").replace(">", "&gt;")
