"""The DC motor of examples/dcmotor behind a motor driver that speaks rtloop's serial protocol.

Three things live here:

- :class:`DriverModel`: what the motor driver board does with each request: apply the
  voltage for one period, answer speed and current. It advances the motor one period per
  request (lock-step with the controller: a hardware *simulator*, so that a run equals its
  simulation; a real motor would move on with time);
- ``python serial_motor.py --link PATH``: the driver as a separate process on a
  pseudo-terminal (``PATH`` links to it, the app's ``port``). While the host enables its
  output, every request is its heartbeat: when none comes for ``--heartbeat-ms``, it turns
  its output off and stays off (safe) until restarted, as ODrive's or moteus' watchdogs do;
- :class:`MotorDriverTwin`: the same :class:`DriverModel` as a ``Runnable``, the device's
  twin: ``rtloop simulate`` runs it in the serial device's place.

The PI controller is the one of examples/dcmotor, loaded from there.
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import sys
import time
import tty
from pathlib import Path

import numpy as np

from rtloop import Runnable
from rtloop.app.modules import load_module_file
from rtloop.io.serial import ENABLED, REQUEST_SYNC, RESPONSE_SYNC, Frame, read_frame


def _dcmotor_file() -> Path:
    """examples/dcmotor/dcmotor.py, or a copy beside this file (an app of your own started from this one)."""
    here = Path(__file__).resolve().parent
    for candidate in (here / "dcmotor.py", here.parent / "dcmotor" / "dcmotor.py"):
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(f"serial_motor.py needs dcmotor.py (the motor and the PI) beside it in {here}: "
                            "copy examples/dcmotor/dcmotor.py there")


_dcmotor = load_module_file("dcmotor", _dcmotor_file())
DcMotor = _dcmotor.DcMotor
PiSpeed = _dcmotor.PiSpeed

COMMANDS = ("voltage_V",)
READINGS = ("speed_rad_s", "current_A")


class DriverModel:
    """The driver board and its motor: one request = one period at the commanded voltage."""

    def __init__(self, initial_speed_rad_s: float = 0.0) -> None:
        self.motor = DcMotor()
        self.motor_u = np.zeros(2)  # [voltage_V, load_torque_Nm]: no load on the shaft
        self.motor_y = np.zeros(2)
        self.motor.initialize(self.motor_u, self.motor_y, 0.0)
        self.motor.speed_rad_s = initial_speed_rad_s  # a shaft already turning when the driver starts

    def exchange(self, voltage_V: float, readings: np.ndarray) -> None:
        """Answer what is measured now, then drive the motor one period at ``voltage_V``."""
        readings[0], readings[1] = self.motor.speed_rad_s, self.motor.current_A
        self.motor_u[0] = voltage_V
        self.motor.calculate(self.motor_u, self.motor_y)


class MotorDriverTwin(Runnable):
    """The serial motor driver's twin: u = [voltage_V] → y = [speed_rad_s, current_A]."""

    n_inputs, n_outputs = 1, 2
    input_names, output_names = COMMANDS, READINGS

    def __init__(self, initial_speed_rad_s: float = 0.0) -> None:
        self.initial_speed_rad_s = float(initial_speed_rad_s)  # the driver's --initial-speed-rad-s

    def prerun(self) -> None:
        self.model = DriverModel(self.initial_speed_rad_s)

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        self.model.exchange(float(u[0]), y)


def serve(master: int, heartbeat_ms: float, log: object = sys.stdout, late_every: int = 0,
          late_ms: float = 0.0, initial_speed_rad_s: float = 0.0) -> None:
    """Answer requests on ``master`` until SIGTERM/SIGINT; go safe when they stop. With ``late_every``
    N > 0, every Nth answer goes out ``late_ms`` late (to see what the app's ``on_missing`` does)."""
    model = DriverModel(initial_speed_rad_s)
    request, response = Frame(REQUEST_SYNC, len(COMMANDS)), Frame(RESPONSE_SYNC, len(READINGS))
    poller = select.poll()
    poller.register(master, select.POLLIN)
    readings = np.zeros(len(READINGS))
    armed = safe = False  # armed: the host enabled the output; safe: the heartbeat stopped (latched)
    requests = 0
    previous_V = 0.0
    last_ns = time.monotonic_ns()
    heartbeat_ns = round(heartbeat_ms * 1e6)
    while True:
        if not read_frame(master, request, poller, heartbeat_ns if armed and not safe else 1_000_000_000):
            if armed and not safe:
                safe = True  # latched: no motion on re-enable, only a restart clears it
                quiet_ms = (time.monotonic_ns() - last_ns) / 1e6
                print(f"motor driver: no request for {quiet_ms:.1f} ms (heartbeat {heartbeat_ms:g} ms): "
                      f"output off, safe after {requests} requests", file=log, flush=True)
            continue
        problem = request.problem()
        if problem is not None:
            print(f"motor driver: bad request ({problem}); ignored", file=log, flush=True)
            continue
        last_ns = time.monotonic_ns()
        if request.enabled != armed and not safe:
            armed = request.enabled
            print(f"motor driver: output {'enabled, heartbeat armed' if armed else 'disabled by the host'} "
                  f"at request {requests}", file=log, flush=True)
        voltage = 0.0 if safe else float(request.values[0])
        model.exchange(voltage, readings)
        requests += 1
        response.values[:] = readings
        response.seal(request.sequence, 0 if safe else ENABLED)
        if late_every and requests % late_every == 0:
            time.sleep(late_ms / 1e3)
        os.write(master, response.buffer)
        if voltage == 0.0 and previous_V != 0.0:  # the host's safe value, or a controller asking for nothing
            print(f"motor driver: output 0 V at request {requests}", file=log, flush=True)
        previous_V = voltage


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="A DC motor driver speaking rtloop's serial protocol on a pty.")
    parser.add_argument("--link", required=True, type=Path, help="symlink to create to the pty (the app's port)")
    parser.add_argument("--heartbeat-ms", type=float, default=50.0, help="go safe after this long without a request")
    parser.add_argument("--priority", type=int, default=0, help="SCHED_FIFO priority (a board answers at once)")
    parser.add_argument("--late-every", type=int, default=0, metavar="N",
                        help="answer every Nth request late (to see what the app's on_missing does)")
    parser.add_argument("--late-ms", type=float, default=2.5, help="how late, with --late-every (ms)")
    parser.add_argument("--initial-speed-rad-s", type=float, default=0.0,
                        help="the shaft's speed when the driver starts (a motor not at rest; the twin's "
                             "twin_args = { initial_speed_rad_s = ... } must say the same)")
    args = parser.parse_args(argv)
    if args.priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.priority))
        except PermissionError:
            print("motor driver: no permission for SCHED_FIFO; answering at normal priority", flush=True)
    master, slave = os.openpty()  # the driver keeps the slave open too: the line stays up between clients
    tty.setraw(slave)
    slave_path = os.ttyname(slave)
    args.link.parent.mkdir(parents=True, exist_ok=True)
    if args.link.is_symlink():
        args.link.unlink()
    os.symlink(slave_path, args.link)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    print(f"motor driver: listening on {slave_path} ({args.link} links to it), heartbeat {args.heartbeat_ms:g} ms",
          flush=True)
    try:
        serve(master, args.heartbeat_ms, late_every=args.late_every, late_ms=args.late_ms,
              initial_speed_rad_s=args.initial_speed_rad_s)
    except KeyboardInterrupt:
        pass
    finally:
        if args.link.is_symlink() and os.readlink(args.link) == slave_path:
            args.link.unlink()
    return 0


if __name__ == "__main__":
    sys.exit(main())
