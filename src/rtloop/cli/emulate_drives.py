"""``rtloop io emulate ethercat``: emulated CiA 402 drives on a network interface (a veth end).

With ``--app`` the drives are those the app file's EtherCAT device declares (identity, PDO
mapping, drive model: the device's twin), so a real run against them equals ``rtloop simulate``;
with ``--slaves N``, N default drives. ``--veth`` makes the veth pair for the emulator's lifetime
(``rtloop.io.drives.veth``).
"""

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from rtloop.io.drives.canopen_node import add_arguments as canopen_arguments
    from rtloop.io.drives.emulator import add_arguments as emulator_arguments

    parser.add_argument("bus", choices=["ethercat", "canopen"], help="the bus to emulate drives on")
    parser.add_argument("--app", help="the drives the app file's EtherCAT device declares (with their drive models)")
    parser.add_argument("--device", help="with --app: which EtherCAT device, when the app has several")
    parser.add_argument("--veth", nargs="?", const="", default=None, metavar="MASTER_END",
                        help="ethercat: make the veth pair first (the master's end MASTER_END; with --app, default "
                        "its interface) and delete it when the emulator ends (root)")
    emulator_arguments(parser)
    canopen_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from rtloop.io.drives.emulator import DriveSpec, serve

    if args.bus == "canopen":
        from rtloop.cli.emulate_canopen import run as run_canopen

        return run_canopen(args)

    interface = args.interface
    master_end = args.veth or ""
    if args.app:
        from rtloop.app.appfile import load_app
        from rtloop.io.drives.ethercat import EthercatDevice

        app = load_app(args.app)
        found = [spec.device for spec in app.devices.values()
                 if isinstance(spec.device, EthercatDevice) and args.device in (None, spec.name)]
        if not found:
            named = f" {args.device!r}" if args.device else ""
            print(f"rtloop io emulate: {args.app}: no EtherCAT device{named} in the app file", file=sys.stderr)
            return 2
        device = found[0]
        drives = device.drive_specs()
        interface = interface or device.emulator_interface
        master_end = master_end or device.interface
    elif args.slaves > 0:
        drives = [DriveSpec() for _ in range(args.slaves)]
    else:
        print("rtloop io emulate: give --app APP.toml or --slaves N", file=sys.stderr)
        return 2
    if not interface:
        print("rtloop io emulate: give --interface (the veth end the drives answer on)", file=sys.stderr)
        return 2
    if args.veth is None:
        return serve(interface, drives, args.log, tuple(args.inject), args.priority)
    from rtloop.io.drives.veth import VethError, delete_veth, make_veth

    if not master_end:
        print("rtloop io emulate: --veth: name the master's end (--veth ecm0), or give --app", file=sys.stderr)
        return 2
    try:
        make_veth(master_end, interface)
    except VethError as error:
        print(f"rtloop io emulate: --veth: {error}", file=sys.stderr)
        return 3
    try:
        return serve(interface, drives, args.log, tuple(args.inject), args.priority)
    finally:
        delete_veth(master_end)
