"""``rtloop doctor [--json]``: is this machine ready for real time, and how to fix what is not?

The checks are :mod:`rtloop.toolbox.doctor`'s, plus whether the device interfaces here
can be opened (``rtloop io list`` has the details). Exit status 1 when any check fails.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rtloop.toolbox.doctor import Check

HELP = "is this machine ready for real time? how to fix what is not"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = "Check whether this machine is ready for real-time loops, and how to fix it (exit 1 when " \
                         "a check fails)."
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")
    parser.add_argument("--cpu", metavar="LIST", default=None,
                        help="the CPUs your tasks are pinned to, e.g. 1 or 2-3 (default: the isolated CPUs, else "
                             "the last CPU): device interrupts handled there are named")
    parser.add_argument("--root", type=Path, default=None,
                        help="read /proc, /sys and /etc under this directory (for testing; default /)")


def run(args: argparse.Namespace) -> int:
    """Print the checks; 1 if any check fails, else 0."""
    from rtloop.toolbox.doctor import LIVE_ROOT, format_human, run_checks, to_json, verdict

    root = LIVE_ROOT if args.root is None else args.root
    task_cpus: tuple[int, ...] | None = None
    if args.cpu is not None:
        from rtloop.linux.rt import parse_cpu_list

        try:
            task_cpus = parse_cpu_list(args.cpu)
        except ValueError:
            task_cpus = ()
        if not task_cpus:
            print(f"rtloop doctor: --cpu {args.cpu!r} is not a CPU list (e.g. 1, 2-3 or 0,2)", file=sys.stderr)
            return 2
    checks = run_checks(root, more=[("devices", lambda: check_devices(root))], task_cpus=task_cpus)
    if args.json:
        print(json.dumps(to_json(checks), indent=2, ensure_ascii=False))
    else:
        print(format_human(checks))
    return 1 if verdict(checks) == "fail" else 0


def check_devices(root: Path) -> Check:
    """Interfaces devices can use (``rtloop io list`` has the details): may this user open them?"""
    from rtloop.io.inventory import list_interfaces
    from rtloop.text import counted
    from rtloop.toolbox.doctor import Check

    interfaces = list_interfaces(root)
    if not interfaces:
        return Check("devices", "ok", "no GPIO chip, CAN interface, spidev, serial line or I2C bus here "
                     "(needed only by apps with [devices])", "")
    blocked = [item for item in interfaces if not item.usable]
    kinds = ", ".join(sorted({item.kind for item in interfaces}))
    if not blocked:
        return Check("devices", "ok", f"{counted(len(interfaces), 'interface')} ({kinds}), all usable (rtloop io list)",
                     "")
    return Check("devices", "warn", f"{len(blocked)} of {counted(len(interfaces), 'interface')} cannot be used now: "
                 + ", ".join(item.path for item in blocked),
                 "; ".join(f"{item.path}: {item.fix}" for item in blocked))
