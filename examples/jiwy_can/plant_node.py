"""The gimbal's drive electronics on a CAN bus, simulated: JIWY's plant behind the declared frames.

    python examples/jiwy_can/plant_node.py --interface vcan0 [--step-size-s 0.01] [--priority 70]

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
"""

from __future__ import annotations

import argparse
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


def open_bus(interface: str) -> socket.socket:
    sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    filters = b"".join(struct.pack("=II", can_id, 0x7FF | 0x80000000)
                       for can_id in (STEERING_PAN, STEERING_TILT, HEARTBEAT))
    sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, filters)
    sock.bind((interface,))
    return sock


class Drive:
    """The drive's logic, apart from the bus: steering frames in, angle frames out, the watchdog."""

    def __init__(self, step_size_s: float, heartbeat_timeout_s: float) -> None:
        Plant(step_size_s=step_size_s).step(np.zeros(2), np.zeros(2))  # warm up: the first answer is not late
        self.plant = Plant(step_size_s=step_size_s)
        self.plant.prerun()
        self.steering = np.zeros(2)  # numpy vectors, as the twin gets them in rtloop simulate
        self.angles = np.zeros(2)
        self.have = [False, False]
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.last_beat_s = time.monotonic()
        self.armed = False  # a drive stays disabled until the first heartbeat; its watchdog runs from then on
        self.safe = True

    def on_frame(self, can_id: int, data: bytes, now_s: float) -> list[bytes]:
        """Take one frame; the angle frames to answer once both steering frames of a cycle are in."""
        if can_id == HEARTBEAT:
            self.last_beat_s = now_s
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
        self.plant.step(self.steering, self.angles)
        return [FRAME.pack(ANGLE_PAN, 8, VALUE.pack(self.angles[0])),
                FRAME.pack(ANGLE_TILT, 8, VALUE.pack(self.angles[1]))]

    def on_quiet(self, now_s: float) -> None:
        """No frame for a while: what a drive's watchdog does when the heartbeat stops (steer zero)."""
        if self.armed and not self.safe and now_s - self.last_beat_s > self.heartbeat_timeout_s:
            self.safe = True
            self.steering[:] = 0.0
            say("heartbeat lost: steering zero (safe)")


def say(text: str) -> None:
    print(f"plant_node: {text}", file=sys.stderr, flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description="JIWY's plant behind CAN frames (a simulated drive)")
    parser.add_argument("--interface", default="vcan0")
    parser.add_argument("--step-size-s", type=float, default=0.01, help="the plant's step (the app's period)")
    parser.add_argument("--heartbeat-timeout-ms", type=float, default=200.0)
    parser.add_argument("--priority", type=int, default=0,
                        help="SCHED_FIFO priority 1-99 to answer at (0: an ordinary process)")
    args = parser.parse_args()
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
        can_id, _length, data = FRAME.unpack(bus.recv(16))
        for answer in drive.on_frame(can_id, data, time.monotonic()):
            bus.send(answer)
    bus.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
