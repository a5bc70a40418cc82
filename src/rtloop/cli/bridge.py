"""``rtloop bridge listener|talker``: a ROS 2 node between a topic and a running app's port.

The nodes are :mod:`rtloop.ros.bridge`'s (imported, with DDS, only when one starts).
"""

from __future__ import annotations

import argparse
import sys
from typing import Literal

from rtloop.ros.types import ROS_TYPES

HELP = "ROS 2 listener/talker nodes between topics and an app's ports"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = "ROS 2 bridge nodes: the listener (an output port → a topic) and the talker (a topic → " \
                         "an input port), each until Ctrl-C."
    kinds = parser.add_subparsers(dest="kind", required=True)
    listener = kinds.add_parser("listener", help="publish an output port on a ROS 2 topic")
    talker = kinds.add_parser("talker", help="feed an input port from a ROS 2 topic")
    for sub in (listener, talker):
        sub.add_argument("--app", required=True, help="name of the running app")
        sub.add_argument("--port", required=True)
        sub.add_argument("--topic", required=True, help="ROS 2 topic, e.g. /jiwy/angles")
        sub.add_argument("--type", default="std_msgs/msg/Float64MultiArray", choices=ROS_TYPES)
        sub.add_argument("--qos", default="reliable", choices=("reliable", "sensor"),
                         help="reliable (ROS 2's default, matches every reader) or sensor (best effort)")
        sub.add_argument("--domain-id", type=int, default=None, help="default: ROS_DOMAIN_ID or 0")
    listener.add_argument("--joint-names", nargs="+", default=[], help="for JointState: one name per value")
    listener.add_argument("--every", type=int, default=1, help="publish every N-th tick")


def run(args: argparse.Namespace) -> int:
    from rtloop.app.specs import RosTopic
    from rtloop.ipc.ports import connect_app
    from rtloop.ros.bridge import BridgeStats, run_bridge

    app = connect_app(args.app, timeout_s=10)
    direction: Literal["publish", "subscribe"] = "publish" if args.kind == "listener" else "subscribe"
    topic = RosTopic(direction, args.topic, args.port, args.type, args.qos,
                     tuple(getattr(args, "joint_names", ())), getattr(args, "every", 1), args.domain_id)
    stats = BridgeStats(topic, None)
    print(f"rtloop bridge {args.kind}: {args.topic} {'←' if direction == 'publish' else '→'} "
          f"{app.name}.{args.port}; Ctrl-C to stop", file=sys.stderr)
    run_bridge(app, topic, stats)
    print(f"rtloop bridge {args.kind}: {stats.messages} messages", file=sys.stderr)
    return 0
