"""``rtloop switch``: change a running task's controller at one release (or run one in shadow).

The request is a write to the task's switch port (``<task>_switch``): logged like any port
write, so ``rtloop replay`` reproduces the switch at the same cycle.
"""

from __future__ import annotations

import argparse

from rtloop.errors import PortValueError

HELP = "switch a running task to another of its controllers at one release"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("app", help="app name (or app file)")
    parser.add_argument("changes", nargs="+", metavar="TASK CONTROLLER | TASK=CONTROLLER",
                        help="the task and the controller to make active; several TASK=CONTROLLER switch at the "
                             "same release, all or none")
    parser.add_argument("--at-cycle", type=int, default=None, metavar="N",
                        help="the release from which the new controller acts (default: about 0.2 s from now); "
                             "counted in the first task's periods")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--shadow", action="store_true",
                      help="run CONTROLLER beside the active one on the same inputs, recorded, actuating nothing")
    mode.add_argument("--promote", action="store_true",
                      help="make the task's shadow controller the active one (CONTROLLER may be left out)")
    mode.add_argument("--stop-shadow", action="store_true", help="stop the task's shadow controller")
    parser.add_argument("--user", type=int, default=None, metavar="UID",
                        help="act on the app of this uid (root only; default: your own apps)")


def run(args: argparse.Namespace) -> int:
    from rtloop.ipc.ports import connect_app
    from rtloop.ipc.switch_requests import Mode, switch

    app = connect_app(args.app, owner_uid=args.user, command="switch")
    promote = args.promote or args.stop_shadow
    mode: Mode = "promote" if args.promote else "stop_shadow" if args.stop_shadow else \
        "shadow" if args.shadow else "active"
    answers = switch(app, dict(parse_changes(args.changes, promote=promote)), at_cycle=args.at_cycle, mode=mode)
    print("\n".join(f"{answer.task}: {answer.said}" for answer in answers))
    late = [answer.task for answer in answers if answer.late]
    if late:
        print(f"rtloop switch: the request reached {', '.join(late)} after the release named: it took effect at "
              "the first release after it (summary.json's switches say which)")
    return 0


def parse_changes(words: list[str], *, promote: bool) -> list[tuple[str, str | None]]:
    """``TASK CONTROLLER`` or ``TASK=CONTROLLER …`` (or a lone ``TASK`` to promote its shadow)."""
    if all("=" in word for word in words):
        pairs: list[tuple[str, str | None]] = []
        for word in words:
            task, _, controller = word.partition("=")
            pairs.append((task, controller or None))
    elif len(words) == 2 and "=" not in words[0]:
        pairs = [(words[0], words[1])]
    elif len(words) == 1 and promote:
        pairs = [(words[0], None)]
    else:
        raise PortValueError(f"switch {' '.join(words)}: give TASK CONTROLLER, or TASK=CONTROLLER for each task")
    tasks = [task for task, _ in pairs]
    if len(set(tasks)) != len(tasks):
        raise PortValueError(f"switch: a task is named twice ({', '.join(tasks)})")
    if not promote and any(controller is None for _, controller in pairs):
        raise PortValueError("switch: name the controller for each task (TASK=CONTROLLER)")
    return pairs
