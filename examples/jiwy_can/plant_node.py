"""The gimbal's drive electronics on a CAN bus, simulated: JIWY's plant behind the declared frames.

    python examples/jiwy_can/plant_node.py --interface vcan0 [--step-size-s 0.01]

Each cycle the controller sends the steering frames (0x201 pan, 0x202 tilt, float64) and the
heartbeat (0x701, a counter). When both steering frames of a cycle are in, this node steps the
plant once and answers with the angle frames (0x181 pan, 0x182 tilt). It is what a drive does:
a drive's own watchdog goes safe when the heartbeat stops, and so does this node — after
``--heartbeat-timeout-ms`` without one it steers zero and says so once on stderr
("heartbeat lost"), until the heartbeat comes back.

It speaks plain SocketCAN (a raw socket), as a microcontroller on the bus would: nothing of
rtloop's runtime. It stops on SIGTERM or Ctrl-C.
"""

from __future__ import annotations

import argparse
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


def main() -> int:
    parser = argparse.ArgumentParser(description="JIWY's plant behind CAN frames (a simulated drive)")
    parser.add_argument("--interface", default="vcan0")
    parser.add_argument("--step-size-s", type=float, default=0.01, help="the plant's step (the app's period)")
    parser.add_argument("--heartbeat-timeout-ms", type=float, default=200.0)
    args = parser.parse_args()
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
    Plant(step_size_s=args.step_size_s).step(np.zeros(2), np.zeros(2))  # warm up: the first answer is not late
    plant = Plant(step_size_s=args.step_size_s)
    plant.prerun()
    steering = np.zeros(2)  # numpy vectors, as the twin gets them in rtloop simulate
    have = [False, False]
    angles = np.zeros(2)
    last_beat_s = time.monotonic()
    armed = False  # a drive stays disabled until the first heartbeat; its watchdog runs from then on
    safe = True
    print(f"plant_node: on {args.interface}, waiting for steering frames", file=sys.stderr, flush=True)
    while running:
        ready, _, _ = select.select([bus], [], [], 0.05)
        now_s = time.monotonic()
        if not ready:
            if armed and not safe and now_s - last_beat_s > args.heartbeat_timeout_ms / 1000:
                safe = True  # what a drive's watchdog does: stop steering
                steering[:] = 0.0
                print("plant_node: heartbeat lost: steering zero (safe)", file=sys.stderr, flush=True)
            continue
        can_id, _length, data = FRAME.unpack(bus.recv(16))
        if can_id == HEARTBEAT:
            last_beat_s = now_s
            if safe:
                safe = False
                print(f"plant_node: heartbeat {'back' if armed else 'seen'}: enabled", file=sys.stderr, flush=True)
                armed = True
            continue
        have[can_id == STEERING_TILT] = True
        steering[can_id == STEERING_TILT] = VALUE.unpack_from(data)[0]
        if all(have):
            have[:] = [False, False]
            plant.step(steering, angles)
            bus.send(FRAME.pack(ANGLE_PAN, 8, VALUE.pack(angles[0])))
            bus.send(FRAME.pack(ANGLE_TILT, 8, VALUE.pack(angles[1])))
    bus.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
