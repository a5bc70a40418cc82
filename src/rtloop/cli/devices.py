"""``rtloop io list [--json]``: the interfaces devices can use here, and whether you may open them."""

from __future__ import annotations

import argparse
import json
import sys

HELP = "GPIO chips, CAN interfaces, spidev, serial lines, I2C buses: may you open them?"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    commands = parser.add_subparsers(dest="io_command", required=True)
    listing = commands.add_parser("list", help="GPIO chips, CAN interfaces, spidev, serial lines, I2C buses")
    listing.add_argument("--json", action="store_true", help="one JSON object per interface, as a list")


def run(args: argparse.Namespace) -> int:
    from rtloop.io.inventory import format_table, list_interfaces

    interfaces = list_interfaces()
    if args.json:
        json.dump([item.to_json() for item in interfaces], sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        print(format_table(interfaces))
    return 0
