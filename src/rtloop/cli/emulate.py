"""``rtloop emulate dynamixel --servos 1,2 --link PATH``: servos that speak the real protocol, on a pty."""

from __future__ import annotations

import argparse

HELP = "servos speaking Dynamixel 2.0 or Feetech on a pseudo-terminal (the servo model)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from rtloop.io.servos.emulator import add_arguments as servo_arguments

    servo_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from rtloop.errors import AppError
    from rtloop.io.servos.emulator import bus_from_arguments
    from rtloop.io.servos.emulator import run as serve

    try:
        if args.app is not None:
            _from_app(args)
        bus_from_arguments(args, lambda text: None)  # what the arguments describe, checked before the pty is made
    except AppError:
        raise
    except ValueError as error:  # bad arguments: one line, exit 2 (not an internal error)
        raise AppError(str(error)) from None
    return serve(args)


def _from_app(args: argparse.Namespace) -> None:
    """The servos, their models, the baud rate and the period of the app's servo device (``--device``)."""
    from rtloop.app.appfile import load_app
    from rtloop.io.servos.bus import ServoBusDevice

    app = load_app(args.app)
    buses = {name: spec for name, spec in app.devices.items() if isinstance(spec.device, ServoBusDevice)}
    if not buses or (args.device and args.device not in buses) or (not args.device and len(buses) > 1):
        raise ValueError(f"--device: {args.app} has the servo devices {sorted(buses)}; name one")
    spec = buses[args.device or next(iter(buses))]
    device = spec.device
    assert isinstance(device, ServoBusDevice)
    args.app_protocol = device.protocol_name
    args.app_ids = [servo.servo_id for servo in device.specs]
    args.app_models = [servo.model.name for servo in device.specs]
    args.app_period_ms = app.tasks[spec.task].config.period_ns / 1e6
    args.app_baudrate = device.config["baudrate"]
