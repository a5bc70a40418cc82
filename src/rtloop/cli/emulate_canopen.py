"""``rtloop io emulate canopen``: an emulated CiA 402 drive node on a SocketCAN interface (vcan0).

With ``--app`` the node is the app file's ``canopen402`` joint (``--node``, default its first): its
identity and its drive model (the device's twin), so a run against it equals ``rtloop simulate``.
"""

from __future__ import annotations

import argparse
import sys

from rtloop.io.drives.sii import Identity


def run(args: argparse.Namespace) -> int:
    from rtloop.io.drives.canopen_node import DEFAULT_IDENTITY, CanopenNode, logger, serve
    from rtloop.io.drives.drive_model import DriveParameters

    interface, node_id = args.interface, args.node
    identity: Identity = DEFAULT_IDENTITY
    parameters = DriveParameters()
    if args.app:
        from rtloop.app.appfile import load_app
        from rtloop.io.drives.canopen import Canopen402Device

        app = load_app(args.app)
        found = [(spec.device, n) for spec in app.devices.values() if isinstance(spec.device, Canopen402Device)
                 and args.device in (None, spec.name) for n in spec.device.nodes if node_id in (0, n.node)]
        if not found:
            print(f"rtloop io emulate: {args.app}: no canopen402 joint with node {node_id or 'any'}", file=sys.stderr)
            return 2
        device, n = found[0]
        interface = interface or device.interface
        node_id, identity, parameters = n.node, n.joint.identity, n.joint.drive
    if not 1 <= node_id <= 127:
        print("rtloop io emulate: give --node 1..127 (or --app)", file=sys.stderr)
        return 2
    if not interface:
        print("rtloop io emulate: give --interface (the CAN interface the node answers on)", file=sys.stderr)
        return 2
    stream = open(args.log, "a", buffering=1) if args.log else sys.stdout  # noqa: SIM115 (for the run)
    node = CanopenNode(node_id, parameters, identity, logger(stream), args.sync_timeout_ms / 1000.0)
    for text in args.inject:
        what, _, at = text.partition("@")
        if what != "fault" or not at.isdigit():
            print(f"rtloop io emulate: --inject {text!r}: for canopen expected fault@N (the Nth SYNC with the "
                  "drive enabled)", file=sys.stderr)
            return 2
        node.inject_at_sync = int(at)
    return serve(interface, node, priority=args.priority)
