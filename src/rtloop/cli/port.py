"""``rtloop port write/read/list``: a thin command line over :mod:`rtloop.ipc.ports`."""

from __future__ import annotations

import argparse
import time

from rtloop.ipc.ports import connect_app, scan_registries


def cli_port(args: argparse.Namespace) -> int:
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
        while printed < args.count:
            ticks, rows = reader.read(args.count - printed)
            for tick, row in zip(ticks.tolist(), rows.tolist(), strict=True):
                print(f"{tick * reader.period_ns / 1e9:.6f} " + " ".join(repr(v) for v in row), flush=True)
            printed += len(ticks)
            if not len(ticks):
                time.sleep(0.02)
    return 0
