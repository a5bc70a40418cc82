"""``rtloop port write/read/list``: a thin command line over :mod:`rtloop.ipc.ports`."""

from __future__ import annotations

import argparse
import re
import time

from rtloop.cli.arguments import at_least_one

HELP = "write to or read from a running app's port"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    port_commands = parser.add_subparsers(dest="port_command", required=True)
    write = port_commands.add_parser("write", help="post values to an input port")
    write.add_argument("app", help="app name (or app file)")
    write.add_argument("port")
    write.add_argument("values", nargs="+", type=float)
    read = port_commands.add_parser("read", help="print what an output port sends, from now on")
    read.add_argument("app", help="app name (or app file)")
    read.add_argument("port")
    read.add_argument("--count", type=at_least_one, default=10, help="rows to print, then exit (default 10)")
    read.add_argument("--queued", action="store_true",
                      help="start with the oldest samples still queued instead of the newest")
    port_commands.add_parser("list", help="list running apps and their ports")
    for sub in (write, read):
        sub.add_argument("--user", type=int, default=None, metavar="UID",
                         help="act on the app of this uid (root only; default: your own apps)")


def run(args: argparse.Namespace) -> int:
    from rtloop.ipc.ports import connect_app, scan_registries

    if args.port_command == "list":
        apps, refused = scan_registries()
        if not apps:
            print("no running apps")
        for app in apps:
            print(f"{app.name} (supervisor pid {app.pid}, uid {app.uid})")
            for name, info in app.ports.items():
                print(f"  {name:<16} {info['direction']:<4} {info['signal']}  ({info['size']} values)")
        for refusal in refused:
            print(f"not listed: {refusal.path.name}: {refusal.reason}")
        return 0
    app = connect_app(args.app, owner_uid=args.user)
    if args.port_command == "write":
        app.write(args.port, args.values)
        return 0
    printed = 0
    with app.reader(args.port) as reader:
        if not args.queued:
            reader.skip_to_newest()  # what the app sends now, not what queued up before anyone read
        names = element_names(app.ports[args.port]["signal"])
        print("t_s".rjust(TIME_WIDTH) + "".join(name.rjust(VALUE_WIDTH) for name in names), flush=True)
        while printed < args.count:
            ticks, rows = reader.read(args.count - printed)
            for tick, row in zip(ticks.tolist(), rows.tolist(), strict=True):  # fixed columns: nothing jumps
                print(f"{tick * reader.period_ns / 1e9:{TIME_WIDTH}.6f}"
                      + "".join(f"{value:{VALUE_WIDTH}.8g}" for value in row), flush=True)
            printed += len(ticks)
            if not len(ticks):
                time.sleep(0.02)
    return 0


TIME_WIDTH = 12
VALUE_WIDTH = 16


def element_names(signal: str) -> list[str]:
    """``plant.y[0:2]`` → ``["plant.y[0]", "plant.y[1]"]`` (the columns of ``port read``)."""
    match = re.fullmatch(r"(\w+)\.([uy])\[(\d+)(?::(\d+))?\]", signal)
    if match is None:
        return [signal]
    task, side, start, stop = match.groups()
    stop_index = int(stop) if stop is not None else int(start) + 1
    return [f"{task}.{side}[{index}]" for index in range(int(start), stop_index)]
