"""``rtloop emulate dynamixel --servos 1,2 --link PATH``: servos that speak the real protocol, on a pty."""

from __future__ import annotations

import argparse

HELP = "servos speaking Dynamixel 2.0 or Feetech on a pseudo-terminal (the servo model)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from rtloop.io.servos.emulator import add_arguments as servo_arguments

    servo_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from rtloop.io.servos.emulator import run as serve

    return serve(args)
