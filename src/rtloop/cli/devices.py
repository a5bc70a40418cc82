"""``rtloop io list [--json] [--ethercat IF] [--canopen IF]``: the interfaces devices can use here, and
whether you may open them; ``rtloop io emulate ethercat``: emulated drives on a veth end (``cli/emulate.py``)."""

from __future__ import annotations

import argparse
import json
import sys

HELP = "GPIO chips, CAN interfaces, spidev, serial lines, I2C buses: may you open them?"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    commands = parser.add_subparsers(dest="io_command", required=True)
    listing = commands.add_parser("list", help="GPIO chips, CAN interfaces, spidev, serial lines, I2C buses")
    listing.add_argument("--json", action="store_true", help="one JSON object per interface, as a list")
    listing.add_argument("--ethercat", action="append", default=[], metavar="IF",
                         help="also scan network interface IF for EtherCAT slaves (sends EtherCAT frames on it; root)")
    listing.add_argument("--canopen", action="append", default=[], metavar="IF",
                         help="also list the CANopen nodes on CAN interface IF (reads 0x1018 by SDO from each node id)")
    from rtloop.cli import emulate_drives as emulate

    emulate.add_arguments(commands.add_parser("emulate", help="emulated CiA 402 drives on a veth end"))


def run(args: argparse.Namespace) -> int:
    if args.io_command == "emulate":
        from rtloop.cli import emulate_drives as emulate

        return emulate.run(args)
    from rtloop.io.inventory import format_table, list_interfaces

    interfaces = list_interfaces()
    if args.ethercat:
        from rtloop.io.drives.scan import ethercat_slaves

        interfaces += [slave for name in args.ethercat for slave in ethercat_slaves(name)]
    if args.canopen:
        from rtloop.io.drives.canopen_scan import canopen_nodes

        interfaces += [node for name in args.canopen for node in canopen_nodes(name)]
    if args.json:
        json.dump([item.to_json() for item in interfaces], sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        print(format_table(interfaces))
    return 0
