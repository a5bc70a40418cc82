"""Emulated EtherCAT CiA 402 drives on a network interface: ``python -m rtloop.io.drives.emulator``.

    ip link add ecm0 type veth peer name ecs0; ip link set ecm0 up; ip link set ecs0 up
    python -m rtloop.io.drives.emulator --interface ecs0 --slaves 2 --log drives.log &
    # or the drives an app file declares, with their drive models (the device's twin):
    rtloop io emulate ethercat --app examples/jiwy_ethercat/jiwy_ethercat.toml --interface ecs0

The master (rtloop's EtherCAT device, pysoem, any SOEM program) opens the other end of the veth
pair. Every frame that comes in passes the emulated slaves in order and goes back out. The log
has one line per event that a test or a person checks: AL state changes ("left OP"), the drive's
own state changes ("quick stop (controlword)", "fault 0x5530: ..."), injected faults.

Fault injection, counted in process-data exchanges with the drive enabled (``--inject``,
repeatable): ``fault:SLAVE@N`` (the drive faults), ``drop:SLAVE@N`` (the slave drops out: answers
nothing more, a cable pulled), ``lose@N`` (that one frame is not answered: lost on the wire; the
slaves took its outputs), ``lose:K@N`` (K frames in a row), ``late:US@N`` (that frame answered US
µs late: the emulator holds it, then answers it and the frames that came meanwhile),
``clock:SLAVE@N`` (the slave's distributed clocks unit stops: as reference clock its time no longer
goes out).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TextIO

from rtloop.io import compiled
from rtloop.io.drives.drive_model import DriveParameters, emulated_drive
from rtloop.io.drives.esc import AL_OP, EmulatedSlave, Segment
from rtloop.io.drives.pdo import DEFAULT_RXPDO, DEFAULT_TXPDO, PdoLayout
from rtloop.io.drives.rawsocket import FRAME_BYTES, interface_problem, open_raw
from rtloop.io.drives.sii import Identity

__all__ = ["DEFAULT_IDENTITY", "DriveSpec", "Emulator", "main"]

DEFAULT_IDENTITY = Identity(vendor=0x00000A7E, product=0x00402402, revision=0x00010000)
"""What an emulated drive says it is unless an app file names another."""


@dataclass(frozen=True)
class DriveSpec:
    """One emulated slave: who it says it is, its mapping, its drive model."""

    identity: Identity = DEFAULT_IDENTITY
    rxpdo: tuple[int, ...] = DEFAULT_RXPDO
    txpdo: tuple[int, ...] = DEFAULT_TXPDO
    parameters: DriveParameters = field(default_factory=DriveParameters)
    name: str = "rtloop emulated CiA 402 drive"
    dc: bool = True
    """Whether it has distributed clocks (its ESI's Dc element; a slave without runs free on the frames)."""


@dataclass(frozen=True)
class Injection:
    what: str
    """``fault``, ``drop``, ``lose``, ``late`` or ``clock``."""
    slave: int
    """The slave (1 the first); for ``lose`` the frames lost in a row, for ``late`` the delay in µs."""
    at_exchange: int


def parse_injection(text: str) -> Injection:
    what, _, rest = text.partition(":") if ":" in text else (text.partition("@")[0], "", "@" + text.partition("@")[2])
    slave_text, _, at_text = rest.partition("@")
    if what not in ("fault", "drop", "lose", "late", "clock") or not at_text.isdigit() or \
            (what != "lose" and not slave_text.isdigit()) or (slave_text and not slave_text.isdigit()):
        raise ValueError(f"--inject {text!r}: expected fault:SLAVE@N, drop:SLAVE@N, clock:SLAVE@N, lose@N, "
                         "lose:K@N or late:US@N")
    injection = Injection(what, int(slave_text or 1), int(at_text))
    if injection.slave < 1:  # (lose:0 would log a loss it never made; slave 0 is none)
        raise ValueError(f"--inject {text!r}: {'K' if what == 'lose' else 'US' if what == 'late' else 'SLAVE'} "
                         "must be at least 1")
    return injection


def injection_problem(text: str, injection: Injection, slaves: int) -> str | None:
    """An injection on a slave the segment does not have (it hit slave 1 instead), or None."""
    if injection.what in ("fault", "drop", "clock") and injection.slave > slaves:
        return f"--inject {text!r}: slave {injection.slave}, but the segment has {slaves} slave(s)"
    return None


class Emulator:
    """Slaves on one interface, answering every EtherCAT frame; ``run`` until stopped."""

    def __init__(self, interface: str, drives: list[DriveSpec], log: Callable[[str], None],
                 injections: tuple[Injection, ...] = ()) -> None:
        self.interface = interface
        self.log = log
        self.slaves = [EmulatedSlave(position, spec.identity, PdoLayout(spec.rxpdo), PdoLayout(spec.txpdo),
                                     emulated_drive(spec.parameters), spec.name, log, dc=spec.dc)
                       for position, spec in enumerate(drives, start=1)]
        self.segment = Segment(self.slaves)
        for injection in injections:
            problem = injection_problem(f"{injection.what}:{injection.slave}@{injection.at_exchange}", injection,
                                        len(self.slaves))
            if problem:
                raise ValueError(problem)
        self.injections = list(injections)
        self.stopped = False
        self.frames = 0
        self.lose_left = 0  # frames still to be lost (lose:K@N)
        self.late_s = 0.0  # how late the frame being answered goes back (late:US@N)

    def _inject(self) -> bool:
        """Carry out injections that are due; False when this frame is to be lost."""
        answer = True
        for injection in list(self.injections):
            on_slave = injection.what in ("fault", "drop", "clock")
            slave = self.slaves[injection.slave - 1] if on_slave else self.slaves[0]  # (checked: serve)
            if slave.al_status & 0x0F != AL_OP or slave.exchanges_enabled < injection.at_exchange:
                continue
            self.injections.remove(injection)
            if injection.what == "fault":
                self.log(f"slave {slave.position}: injected drive fault at exchange {slave.exchanges_enabled}")
                slave.drive.inject_fault()
            elif injection.what == "drop":
                self.log(f"slave {slave.position}: injected drop-out at exchange {slave.exchanges_enabled}: "
                         "it answers nothing from now on")
                slave.dropped = True
            elif injection.what == "clock":
                self.log(f"slave {slave.position}: injected loss of its distributed clocks unit at exchange "
                         f"{slave.exchanges_enabled}")
                slave.dc = None
            elif injection.what == "late":
                self.log(f"injected late answer at exchange {slave.exchanges_enabled}: answered "
                         f"{injection.slave} µs late")
                self.late_s = injection.slave / 1e6
            else:
                count = injection.slave
                self.log(f"injected lost frame at exchange {slave.exchanges_enabled}: not answered" +
                         (f", nor the {count - 1} after it" if count > 1 else ""))
                self.lose_left = count
        if self.lose_left:
            self.lose_left -= 1
            answer = False
        return answer

    def _tick(self) -> None:
        self.segment.tick(time.monotonic_ns())

    def run(self) -> None:
        # blocking, a receive ending after a kernel tick without frames (SO_RCVTIMEO): one syscall per
        # receive and per send, where Python's timeout polls before each
        sock = open_raw(self.interface, receive_timeout_us=1000)
        buffer = bytearray(FRAME_BYTES + 64)
        whole = memoryview(buffer)
        self.log(f"emulating {len(self.slaves)} EtherCAT slave(s) on {self.interface}: " +
                 "; ".join(f"{s.position}: {s.identity.describe()}{'' if s.dc else ', no distributed clocks'}"
                           for s in self.slaves) +
                 (" (process data in C)" if self.segment.compiled else
                  f" (process data in Python: {compiled.why_python() or 'the drives are not compiled'})"))
        try:
            while not self.stopped:
                try:
                    size = sock.recv_into(buffer)
                except (TimeoutError, BlockingIOError):
                    size = 0
                except InterruptedError:
                    continue
                if size < 16 or buffer[12:14] != b"\x88\xa4":
                    self._tick()  # after the frames waiting are served: a late emulator is not a late master
                    continue
                frame = whole[:size]  # in place: no copy
                self.frames += 1
                if not self.segment.process(frame):
                    continue
                self._tick()
                if (self.injections or self.lose_left) and not self._inject():
                    continue
                if self.late_s:  # held: the frames that come meanwhile wait in the socket
                    time.sleep(self.late_s)
                    self.late_s = 0.0
                frame[6] |= 0x02  # the first slave marks the source address as it forwards the frame
                try:
                    sock.send(frame)
                except OSError as error:
                    self.log(f"send failed: {error}")
        finally:
            sock.close()
            self.log("emulator stopped")


def _logger(stream: TextIO) -> Callable[[str], None]:
    def log(text: str) -> None:  # CLOCK_MONOTONIC seconds: the clock of a run's timing.csv (T0, releases)
        stream.write(f"{time.monotonic():.6f} {text}\n")
        stream.flush()
    return log


def serve(interface: str, drives: list[DriveSpec], log_path: str | None = None, inject: tuple[str, ...] = (),
          priority: int = 0) -> int:
    """Run the emulator until SIGTERM or SIGINT; the exit code (2 bad input, 3 interface not usable)."""
    try:
        injections = tuple(parse_injection(text) for text in inject)
    except ValueError as error:
        print(f"emulator: {error}", file=sys.stderr)
        return 2
    for text, injection in zip(inject, injections, strict=True):
        problem = injection_problem(text, injection, len(drives))
        if problem:
            print(f"emulator: {problem}", file=sys.stderr)
            return 2
    problem = interface_problem(interface)
    if problem:
        print(f"emulator: {problem}", file=sys.stderr)
        return 3
    stream: TextIO = open(log_path, "a", buffering=1) if log_path else sys.stdout  # noqa: SIM115 (for the run)
    emulator = Emulator(interface, drives, _logger(stream), injections)

    def stop(_signum: int, _frame: object) -> None:
        emulator.stopped = True
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    if priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except OSError as error:
            emulator.log(f"SCHED_FIFO {priority} refused ({error.strerror}): running at normal priority")
    try:
        emulator.run()
    except OSError as error:
        why = ("no permission for a raw socket (run as root, or give python CAP_NET_RAW)"
               if isinstance(error, PermissionError) else str(error))
        print(f"emulator: {interface}: {why}", file=sys.stderr)
        return 3
    finally:
        if stream is not sys.stdout:
            stream.close()
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--interface", help="the veth end the slaves answer on (e.g. ecs0)")
    parser.add_argument("--slaves", type=int, default=0, help="this many default drives")
    parser.add_argument("--log", help="append the log here (default: standard output)")
    parser.add_argument("--inject", action="append", default=[], metavar="WHAT",
                        help="fault:SLAVE@N, drop:SLAVE@N, clock:SLAVE@N, lose@N, lose:K@N (K frames in a row) or "
                        "late:US@N (answered US µs late); N: exchanges with the drive enabled")
    parser.add_argument("--priority", type=int, default=0,
                        help="run at SCHED_FIFO this priority (a drive must answer within the master's timeout)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rtloop.io.drives.emulator", description=__doc__.split("\n")[0])
    add_arguments(parser)
    args = parser.parse_args(argv)
    if args.slaves <= 0 or not args.interface:
        print("emulator: give --interface IF and --slaves N (or use rtloop io emulate ethercat --app APP)",
              file=sys.stderr)
        return 2
    return serve(args.interface, [DriveSpec() for _ in range(args.slaves)], args.log, tuple(args.inject),
                 args.priority)


if __name__ == "__main__":
    sys.exit(main())
