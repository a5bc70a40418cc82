"""``rtloop port write/read/list``: a thin command line over :mod:`rtloop.ipc.ports`."""

from __future__ import annotations

import argparse
import re
import time
from typing import Any

from rtloop.cli.arguments import at_least_one
from rtloop.text import clip, counted

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
                print("\n".join(describe_port(name, info)))
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
        names = column_names(app.ports[args.port])
        widths = [max(VALUE_WIDTH, len(name) + 2) for name in names]
        print("t_s".rjust(TIME_WIDTH) + "".join(name.rjust(width) for name, width in zip(names, widths, strict=False)),
              flush=True)
        while printed < args.count:
            ticks, rows = reader.read(args.count - printed)
            for tick, row in zip(ticks.tolist(), rows.tolist(), strict=True):  # fixed columns: nothing jumps
                print(f"{tick * reader.period_ns / 1e9:{TIME_WIDTH}.6f}"
                      + "".join(f"{value:{width}.8g}" for value, width in zip(row, widths, strict=False)), flush=True)
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


def column_names(info: dict[str, Any]) -> list[str]:
    """The columns of ``port read``: each value as the runnable names it, with the signal and unit
    (``speed_rad_s (plant.y[0]) [rad/s]``), or the signal alone where the registry names none."""
    signals = element_names(_printable(info.get("signal"), limit=200))
    names, units = _strings(info.get("names"), len(signals)), _strings(info.get("units"), len(signals))
    return [(f"{name} ({signal})" if name else signal) + (f" [{unit}]" if unit else "")
            for signal, name, unit in zip(signals, names, units, strict=True)]


def describe_port(name: str, info: dict[str, Any]) -> list[str]:
    """The lines of ``rtloop port list`` for one port of a registry: direction, signal, size, and
    the range and unit of its values. One range and unit for all values: on the port's line
    (``range [-1.5, 1.5] rad``); else one line per value, named as the runnable names it.

    The registry is another process's file (root lists other users' apps): what it says is
    shown, made printable, and a field of the wrong shape is left out, never a traceback."""
    info = info if isinstance(info, dict) else {}
    size = info.get("size")
    size = size if isinstance(size, int) and 0 < size <= MAX_VALUES_LISTED else None
    head = (f"  {_printable(name):<16} {_printable(info.get('direction')):<4} {_printable(info.get('signal'))}"
            f"  ({counted(size, 'value') if size else '? values'})")
    if size is None:
        return [head]
    ranges = _ranges(info.get("range"), size)
    units = _strings(info.get("units"), size)
    names = _strings(info.get("names"), size)
    details = [" ".join(part for part in (_range_text(ranges[i]), units[i]) if part) for i in range(size)]
    if len(set(details)) == 1:
        return [head + (f"  {details[0]}" if details[0] else "")]
    labels = [names[i] or f"[{i}]" for i in range(size)]
    width = max(len(label) for label in labels)
    return [head] + [f"      {label:<{width}}  {detail or '-'}" for label, detail in zip(labels, details, strict=True)]


MAX_VALUES_LISTED = 1024
"""A port with more values than this is listed without them (a registry is not to flood a terminal)."""


def _ranges(value: object, size: int) -> list[tuple[float, float] | None]:
    """The registry's ``range`` (``[lo, hi]``, each a number or one per value) as one pair per value."""
    if not isinstance(value, list) or len(value) != 2:
        return [None] * size
    bounds = []
    for bound in value:
        if _is_number(bound):
            bounds.append([float(bound)] * size)
        elif isinstance(bound, list) and len(bound) == size and all(map(_is_number, bound)):
            bounds.append([float(b) for b in bound])
        else:
            return [None] * size
    return list(zip(*bounds, strict=True))


def _range_text(pair: tuple[float, float] | None) -> str:
    return "" if pair is None else f"range [{pair[0]:g}, {pair[1]:g}]"


def _strings(value: object, size: int) -> list[str]:
    """One printable string per value ('' where the registry has none)."""
    if not isinstance(value, list) or len(value) != size:
        return [""] * size
    return [_printable(item) if isinstance(item, str) else "" for item in value]


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _printable(value: object, limit: int = 40) -> str:
    """At most ``limit`` characters, control characters (a terminal's escape sequences) as '?'."""
    text = value if isinstance(value, str) else "?"
    return clip("".join(c if c.isprintable() else "?" for c in text), limit)
