"""The servo model on a pseudo-terminal: ``rtloop emulate dynamixel --servos 1,2 --link PATH``.

One process, N servos on one bus (:class:`~.model.BusModel`), answering on the pty's master
side; the app's ``port`` is the slave (``--link`` makes a symbolic link to it). It prints one
line per event the tests and a person watch for: listening, torque on/off, a hardware error,
a servo gone silent. ``--app FILE`` takes the servos, their models, the baud rate and the period
from an app's servo device, so the model moves one app period per sync read, as the twin does.
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import sys
import tty
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rtloop.io.servos.tables import FAMILIES

if TYPE_CHECKING:
    from rtloop.io.servos.model import BusModel


def _id_at(text: str, what: str) -> tuple[int, int, int]:
    """``ID@N`` or ``ID@N:BITS`` → (id, n, bits)."""
    try:
        head, _, bits = text.partition(":")
        servo_id, _, count = head.partition("@")
        return int(servo_id), int(count), int(bits, 0) if bits else 0x20
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what}: expected ID@N (servo ID, after N sync reads), "
                                         f"got {text!r}") from None


def _limits(text: str) -> tuple[int, int, int]:
    """``ID:LOW..HIGH`` → (id, low, high), in ticks."""
    try:
        servo_id, _, bounds = text.partition(":")
        low, _, high = bounds.partition("..")
        return int(servo_id), int(low), int(high)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ID:LOW..HIGH (ticks), got {text!r}") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("protocol", nargs="?", choices=sorted(FAMILIES), help="the bus's protocol (or --app)")
    parser.add_argument("--link", required=True, type=Path, help="symbolic link to make to the pty (the app's port)")
    parser.add_argument("--servos", default="", help="servo IDs, e.g. 1,2 (or --app)")
    parser.add_argument("--model", default="", help="model of every servo (XM430-W350, STS3215, …), or one per "
                        "servo separated by commas")
    parser.add_argument("--period-ms", type=float, default=None, help="the app's period: the servos move this "
                        "long per sync read (default 2, or the app's)")
    parser.add_argument("--baudrate", type=int, default=None, help="the rate the servos are set to (default 1000000)")
    parser.add_argument("--app", type=Path, help="take servos, models, baud rate and period from this app file")
    parser.add_argument("--device", default="", help="with --app: which servo device (default: the only one)")
    parser.add_argument("--silent", action="append", default=[], metavar="ID@N",
                        help="servo ID answers N sync reads, then nothing (repeatable)")
    parser.add_argument("--hardware-error", action="append", default=[], metavar="ID@N[:BITS]",
                        help="servo ID reports a hardware error (default 0x20, overload) after N sync reads")
    parser.add_argument("--position-limits", action="append", default=[], metavar="ID:LOW..HIGH", type=_limits,
                        help="servo ID's min/max position limits in ticks (default the whole turn; repeatable)")
    parser.add_argument("--priority", type=int, default=0, help="SCHED_FIFO priority (servos answer at once)")


def bus_from_arguments(args: argparse.Namespace, log: Any) -> tuple[str, BusModel]:
    """The bus model the arguments describe (``ValueError`` naming what is wrong)."""
    from rtloop.io.servos.model import Faults, build_bus

    protocol, ids, models = args.protocol, [], []
    period_ms, baud = args.period_ms, args.baudrate
    if args.app is not None:  # what cli/emulate.py read from the app file
        protocol, ids, models = args.app_protocol, args.app_ids, args.app_models
        period_ms, baud = period_ms or args.app_period_ms, baud or args.app_baudrate
    if not protocol:
        raise ValueError("name the protocol (dynamixel or feetech) or give --app")
    if args.servos:
        ids = [int(text) for text in args.servos.split(",")]
    if args.model:
        models = args.model.split(",")
    if not ids:
        raise ValueError("--servos: no servo IDs (e.g. --servos 1,2)")
    if not models:
        models = [next(iter(FAMILIES[protocol].models))]
    if len(models) not in (1, len(ids)):
        raise ValueError(f"--model: {len(models)} models for {len(ids)} servos")
    faults: dict[int, Any] = {}
    for text in args.silent:
        servo_id, count, _bits = _id_at(text, "--silent")
        faults[servo_id] = Faults(silent_after_reads=count)
    for text in args.hardware_error:
        servo_id, count, bits = _id_at(text, "--hardware-error")
        old = faults.get(servo_id, Faults())
        faults[servo_id] = Faults(old.silent_after_reads, count, bits)
    bus = build_bus(protocol, ids, models, (period_ms or 2.0) / 1e3, faults=faults, log=log,
                    baud_rate=baud or 1_000_000)
    for servo_id, low, high in args.position_limits:
        if servo_id not in bus.servos:
            raise ValueError(f"--position-limits: no servo {servo_id} on this bus (servos {', '.join(map(str, ids))})")
        bus.servos[servo_id].set("min_position", low)
        bus.servos[servo_id].set("max_position", high)
    return protocol, bus


def serve(master: int, bus: BusModel) -> None:
    """Answer what comes on ``master`` until SIGTERM/SIGINT."""
    poller = select.poll()
    poller.register(master, select.POLLIN)
    while True:
        if not poller.poll(1000):
            continue
        try:
            data = os.read(master, 4096)
        except OSError:  # no client has the slave open (EIO on Linux): wait for one
            poller.poll(50)
            continue
        answers = bus.receive(data)
        if answers:
            os.write(master, answers)


def run(args: argparse.Namespace) -> int:
    def log(text: str) -> None:
        print(f"servo model: {text}", flush=True)

    protocol, bus = bus_from_arguments(args, log)
    if args.priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.priority))
        except PermissionError:
            log("no permission for SCHED_FIFO; answering at normal priority")
    master, slave = os.openpty()  # the model keeps the slave open too: the line stays up between clients
    tty.setraw(slave)
    slave_path = os.ttyname(slave)
    link: Path = args.link
    link.parent.mkdir(parents=True, exist_ok=True)
    if link.is_symlink():
        link.unlink()
    os.symlink(slave_path, link)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    servos = ", ".join(f"{servo.servo_id} ({servo.model.name})" for servo in bus.servos.values())
    print(slave_path, flush=True)
    log(f"{protocol} servos {servos} listening on {slave_path} ({link} links to it), "
        f"{bus.period_s * 1e3:g} ms per sync read")
    try:
        serve(master, bus)
    except KeyboardInterrupt:
        pass
    finally:
        if link.is_symlink() and os.readlink(link) == slave_path:
            link.unlink()
    return 0
