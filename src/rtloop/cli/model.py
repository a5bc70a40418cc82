"""``rtloop model info|build PATH``: inspect or build a 20-sim model or an FMU."""

from __future__ import annotations

import argparse
from pathlib import Path

from rtloop.cli.arguments import BadInput

HELP = "inspect or build a 20-sim model or an FMU"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    model_commands = parser.add_subparsers(dest="model_command", required=True)
    model_commands.add_parser("info", help="inputs, outputs, step size, kind (20-sim folder, FMU, python:)"
                              ).add_argument("path")
    build = model_commands.add_parser(
        "build", help="compile a 20-sim folder into its cached library, or an FMU source folder "
                      "(modelDescription.xml + sources/*.c) into an .fmu (default in the cache, never the source tree)")
    build.add_argument("path")
    build.add_argument("--out", type=Path, default=None, metavar="FILE.fmu",
                       help="where an FMU source folder's .fmu goes (default: ~/.cache/rtloop/fmu/<folder>.fmu)")


def run(args: argparse.Namespace) -> int:
    from rtloop import models

    try:
        if args.model_command == "info":
            text = models.cli_model_info(args.path)
        else:
            text = models.cli_model_build(args.path, args.out)
    except models.ModelError as error:  # the model the user named cannot be used: bad input
        raise BadInput(str(error)) from error
    print(text)
    return 0
