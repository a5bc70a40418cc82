"""``rtloop service APP.toml``: a systemd unit that runs an app until it is stopped.

The unit is printed (or written with ``--install``) with a comment above every setting saying
why it is there (:mod:`rtloop.toolbox.service_unit` writes it; the supervisor's module is imported only then).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import Any

from rtloop.cli.arguments import EXIT_FAILED, BadInput
from rtloop.toolbox.service_unit import (
    CPU_LIST_PATTERN,
    DEFAULT_KEEP_S,
    STATE_ROOT,
    SYSTEMD_UNIT_DIRS,
    UNIT_DIR,
    USER_PATTERN,
    ServiceOptions,
    default_out,
    install,
    parse_cpu_list,
    render_unit,
    unit_name,
)

HELP = "a systemd unit that runs an app until stopped (--install writes it)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = "Print a systemd unit that runs an app until stopped (or install it with --install)."
    parser.add_argument("app", help="app file (TOML)")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR",
                        help=f"recordings of the current run (default {STATE_ROOT}/APP/latest)")
    parser.add_argument("--keep", type=float, default=DEFAULT_KEEP_S, metavar="S",
                        help=f"seconds of recording kept, plus the cycles around faults (default {DEFAULT_KEEP_S:g})")
    parser.add_argument("--user", default=None, metavar="NAME", help="run as this user instead of root")
    parser.add_argument("--supervisor-cpus", default=None, metavar="LIST",
                        help="CPUs for the supervisor and bridges, e.g. 0 or 0,2-3 (default: leave unset)")
    parser.add_argument("--install", action="store_true", help="write the unit instead of printing it")
    parser.add_argument("--unit-dir", type=Path, default=UNIT_DIR, metavar="DIR",
                        help=f"where --install writes (default {UNIT_DIR})")
    parser.add_argument("--force", action="store_true", help="with --install: replace a different existing unit")


def check_options(args: argparse.Namespace) -> None:
    """The first problem with the options, as a :class:`BadInput`."""
    if not args.keep > 0 or not math.isfinite(args.keep):
        raise BadInput(f"--keep {args.keep:g}: expected seconds > 0")
    if args.user is not None and not USER_PATTERN.match(args.user):
        raise BadInput(f"--user {args.user!r}: not a user name")
    if args.supervisor_cpus is not None and not CPU_LIST_PATTERN.match(args.supervisor_cpus):
        raise BadInput(f"--supervisor-cpus {args.supervisor_cpus!r}: expected a CPU list such as 0 or 0,2-3")
    if args.supervisor_cpus is not None and not parse_cpu_list(args.supervisor_cpus):
        raise BadInput(f"--supervisor-cpus {args.supervisor_cpus!r}: a range runs low-high")
    for option, path in (("app file", args.app), ("--out", args.out)):
        if path is not None and any(not c.isprintable() for c in str(path)):
            raise BadInput(f"{option} {str(path)!r}: contains a control character")
    if args.out is not None and Path(args.out).absolute() == Path("/"):
        raise BadInput("--out /: choose a folder of its own")
    domain = os.environ.get("ROS_DOMAIN_ID")
    if domain is not None and not domain.isdigit():
        raise BadInput(f"ROS_DOMAIN_ID={domain!r} in the environment: expected a number")


def load_as_service_user(app_file: Path, user: str | None) -> Any:
    """Load the app as the service will, as ``user`` (root by default) without sudo: refuse now,
    with the fix, code it would refuse at every start (exit 2, so systemd would leave it failed)."""
    import pwd

    from rtloop.app.appfile import CodeRefused, load_app
    from rtloop.app.modules import trusting_only

    try:
        uid = pwd.getpwnam(user).pw_uid if user is not None else 0
    except KeyError:
        raise BadInput(f"--user {user!r}: no such user") from None
    try:
        with trusting_only(uid, "root" if uid == 0 else f"{user} (uid {uid}) or root"):
            return load_app(app_file)
    except CodeRefused as error:
        owner = _owner_name(app_file)
        fix = f"run the service as {owner} (--user {owner}) or " if owner not in (None, "root", user) else ""
        raise BadInput(f"the service, run as {user or 'root'}, would refuse the app's code: {error.problem}; "
                       f"{fix}copy the app to a folder only root can write (e.g. /opt/rtloop/APP)") from None


def _owner_name(path: Path) -> str | None:
    import pwd

    try:
        return pwd.getpwuid(path.absolute().parent.stat().st_uid).pw_name
    except (OSError, KeyError):
        return None


def run(args: argparse.Namespace) -> int:
    """Print the unit, or install it and print what to do next; 1 when it cannot be written."""
    from rtloop.app.appfile import load_app
    check_options(args)
    app = load_as_service_user(Path(args.app), args.user) if args.install else load_app(args.app)
    options = ServiceOptions(
        app_file=Path(args.app).absolute(),
        out=Path(args.out).absolute() if args.out is not None else default_out(app),
        keep_s=args.keep,
        user=args.user,
        supervisor_cpus=args.supervisor_cpus,
        ros_domain_id=os.environ.get("ROS_DOMAIN_ID"),
    )
    text = render_unit(app, options)
    if not args.install:
        sys.stdout.write(text)
        return 0
    if not args.unit_dir.is_dir():
        raise BadInput(f"--unit-dir {args.unit_dir}: no such folder (create it, or leave --unit-dir out "
                       f"to install into {UNIT_DIR})")
    path = args.unit_dir / unit_name(app)
    try:
        message = install(text, path, force=args.force)
    except OSError as error:
        print(f"rtloop service: cannot write {path}: {error.strerror}", file=sys.stderr)
        return EXIT_FAILED
    print(message)
    if args.unit_dir.resolve() in SYSTEMD_UNIT_DIRS:
        print("next:")
        print("  systemctl daemon-reload")
    else:  # systemd never reads this folder by itself: link the file (which also reloads)
        print(f"next (systemd does not look in {args.unit_dir} by itself):")
        print(f"  systemctl link {path.absolute()}")
    print(f"  systemctl enable --now {unit_name(app)}")
    print(f"  journalctl -u {unit_name(app)} -f")
    return 0
