"""The gimbal's drive electronics on a CAN bus, simulated: JIWY's plant behind the declared frames.

    python examples/jiwy_can/plant_node.py --interface vcan0 [--step-size-s 0.01] [--priority 70]
                                           [--late-log late.jsonl] [--late-ms 20]

Each cycle the controller sends the steering frames (0x201 pan, 0x202 tilt, float64) and the
heartbeat (0x701, a counter). When both steering frames of a cycle are in, this node steps the
plant once and answers with the angle frames (0x181 pan, 0x182 tilt). It is what a drive does:
a drive's own watchdog goes safe when the heartbeat stops, and so does this node — after
``--heartbeat-timeout-ms`` without one it steers zero and says so once on stderr
("heartbeat lost"), until the heartbeat comes back.

It speaks plain SocketCAN (a raw socket), as a microcontroller on the bus would: nothing of
rtloop's runtime. It stops on SIGTERM or Ctrl-C.

A real drive answers within microseconds whatever the computer does; this one is a Linux
process, so ``--priority N`` runs it at ``SCHED_FIFO`` priority N (root or CAP_SYS_NICE), below the
controller's: the controller's CAN read waits for the answer, and an ordinary process answering
behind the supervisor's recording work would make the controller's cycle end late.

Even so it can be starved: a machine so busy that the node gets no CPU (an emulated test guest
whose host stalls it for hundreds of ms) answers late, and the controller's read times out —
a fault of the stand-in, not of the loop. So the node measures itself: for each answer, the
time from the arrival of the steering frame that completed it (the kernel's receive time of
that frame on the node's socket, ``SO_TIMESTAMPNS_NEW``) to the answer sent. With ``--late-log
PATH`` every answer later than ``--late-ms`` is appended to PATH as one JSON line: which
exchange it was (0 for the first pair of steering frames, one a cycle), the heartbeat counter
last seen before it, and how late it was.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import select
import signal
import socket
import struct
import sys
import time

import numpy as np
from jiwy_can_models import Plant

STEERING_PAN, STEERING_TILT, HEARTBEAT = 0x201, 0x202, 0x701
ANGLE_PAN, ANGLE_TILT = 0x181, 0x182
FRAME = struct.Struct("=IB3x8s")  # struct can_frame
VALUE = struct.Struct("<d")
# The kernel's receive time of each frame: SO_TIMESTAMPNS_NEW (Linux 5.1+; Python has no name for it)
# gives a 64-bit struct __kernel_timespec on every architecture, CLOCK_REALTIME.
SO_TIMESTAMPNS_NEW = 64
TIMESPEC = struct.Struct("=qq")
ANCILLARY_SIZE = socket.CMSG_SPACE(TIMESPEC.size)


def open_bus(interface: str) -> socket.socket:
    sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    filters = b"".join(struct.pack("=II", can_id, 0x7FF | 0x80000000)
                       for can_id in (STEERING_PAN, STEERING_TILT, HEARTBEAT))
    sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, filters)
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS_NEW, 1)  # when each frame arrived, for Lateness
    sock.bind((interface,))
    return sock


def receive(sock: socket.socket) -> tuple[bytes, int]:
    """One frame and when it arrived on this socket (ns, CLOCK_REALTIME; now if the kernel gave no time)."""
    frame, ancillary, _flags, _address = sock.recvmsg(FRAME.size, ANCILLARY_SIZE)
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS_NEW and len(data) >= TIMESPEC.size:
            seconds, nanoseconds = TIMESPEC.unpack_from(data)
            return frame, seconds * 1_000_000_000 + nanoseconds
    return frame, time.time_ns()  # an answer then looks punctual: never an excuse it did not earn


class Drive:
    """The drive's logic, apart from the bus: steering frames in, angle frames out, the watchdog."""

    def __init__(self, step_size_s: float, heartbeat_timeout_s: float) -> None:
        Plant(step_size_s=step_size_s).step(np.zeros(2), np.zeros(2))  # warm up: the first answer is not late
        self.plant = Plant(step_size_s=step_size_s)
        self.plant.prerun()
        self.steering = np.zeros(2)  # numpy vectors, as the twin gets them in rtloop simulate
        self.angles = np.zeros(2)
        self.have = [False, False]
        self.exchanges = 0  # pairs of steering frames answered: one a cycle of the controller
        self.last_heartbeat: int | None = None  # the counter byte of the newest heartbeat
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.last_beat_s = time.monotonic()
        self.armed = False  # a drive stays disabled until the first heartbeat; its watchdog runs from then on
        self.safe = True

    def on_frame(self, can_id: int, data: bytes, now_s: float) -> list[bytes]:
        """Take one frame; the angle frames to answer once both steering frames of a cycle are in."""
        if can_id == HEARTBEAT:
            self.last_beat_s = now_s
            self.last_heartbeat = data[0]
            if self.safe:
                self.safe = False
                say(f"heartbeat {'back' if self.armed else 'seen'}: enabled")
                self.armed = True
            return []
        axis = 1 if can_id == STEERING_TILT else 0  # an int: a bool would index a numpy vector as a mask
        self.have[axis] = True
        self.steering[axis] = VALUE.unpack_from(data)[0]
        if not all(self.have):
            return []
        self.have = [False, False]
        self.exchanges += 1
        self.plant.step(self.steering, self.angles)
        return [FRAME.pack(ANGLE_PAN, 8, VALUE.pack(self.angles[0])),
                FRAME.pack(ANGLE_TILT, 8, VALUE.pack(self.angles[1]))]

    def on_quiet(self, now_s: float) -> None:
        """No frame for a while: what a drive's watchdog does when the heartbeat stops (steer zero)."""
        if self.armed and not self.safe and now_s - self.last_beat_s > self.heartbeat_timeout_s:
            self.safe = True
            self.steering[:] = 0.0
            say("heartbeat lost: steering zero (safe)")


class Lateness:
    """The node's own measure of being starved: answers later than ``late_ms`` after the frame
    that asked for them arrived, one JSON line each in ``path`` (written at once: a test reads
    it after the node is gone, however it ended)."""

    def __init__(self, path: str, late_ms: float) -> None:
        self.file = open(path, "a", buffering=1)  # noqa: SIM115 - open for the node's life, line by line
        self.late_ns = int(late_ms * 1e6)

    def answered(self, exchange: int, heartbeat: int | None, arrived_ns: int, answered_ns: int) -> None:
        if answered_ns - arrived_ns > self.late_ns:
            self.file.write(json.dumps({"exchange": exchange, "heartbeat_before": heartbeat,
                                        "late_ms": (answered_ns - arrived_ns) / 1e6}) + "\n")

    def close(self) -> None:
        self.file.close()


def say(text: str) -> None:
    print(f"plant_node: {text}", file=sys.stderr, flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description="JIWY's plant behind CAN frames (a simulated drive)")
    parser.add_argument("--interface", default="vcan0")
    parser.add_argument("--step-size-s", type=float, default=0.01, help="the plant's step (the app's period)")
    parser.add_argument("--heartbeat-timeout-ms", type=float, default=200.0)
    parser.add_argument("--priority", type=int, default=0,
                        help="SCHED_FIFO priority 1-99 to answer at (0: an ordinary process)")
    parser.add_argument("--late-log", help="append each answer later than --late-ms here (JSON lines)")
    parser.add_argument("--late-ms", type=float, default=20.0,
                        help="how late an answer is written to --late-log (from its frame's arrival)")
    args = parser.parse_args()
    for option, value, least in (("--step-size-s", args.step_size_s, "above 0"),
                                 ("--heartbeat-timeout-ms", args.heartbeat_timeout_ms, "0 or more"),
                                 ("--late-ms", args.late_ms, "0 or more")):
        if not math.isfinite(value) or value < 0 or (value == 0 and least == "above 0"):
            print(f"plant_node: {option} {value}: expected a finite number, {least}", file=sys.stderr)
            return 2
    if args.priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.priority))
        except (OSError, ValueError) as error:
            print(f"plant_node: --priority {args.priority}: {getattr(error, 'strerror', None) or error}",
                  file=sys.stderr)
            return 2
    try:
        bus = open_bus(args.interface)
    except OSError as error:
        print(f"plant_node: cannot open CAN interface {args.interface!r}: {error.strerror or error}", file=sys.stderr)
        return 2
    try:
        lateness = Lateness(args.late_log, args.late_ms) if args.late_log else None
    except OSError as error:
        print(f"plant_node: --late-log {args.late_log}: {error.strerror or error}", file=sys.stderr)
        return 2
    running = True

    def stop(_signum: int, _frame: object) -> None:
        nonlocal running
        running = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    drive = Drive(args.step_size_s, args.heartbeat_timeout_ms / 1000)
    say(f"on {args.interface}, waiting for steering frames")
    while running:
        ready, _, _ = select.select([bus], [], [], 0.05)
        if not ready:
            drive.on_quiet(time.monotonic())
            continue
        frame, arrived_ns = receive(bus)
        can_id, _length, data = FRAME.unpack(frame)
        answers = drive.on_frame(can_id, data, time.monotonic())
        for answer in answers:
            bus.send(answer)
        if answers and lateness is not None:
            lateness.answered(drive.exchanges - 1, drive.last_heartbeat, arrived_ns, time.time_ns())
    bus.close()
    if lateness is not None:
        lateness.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
