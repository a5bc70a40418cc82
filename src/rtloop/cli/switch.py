"""``rtloop switch``: change a running task's controller at one release (or run one in shadow).

The request is a write to the task's switch port (``<task>_switch``): logged like any port
write, so ``rtloop replay`` reproduces the switch at the same cycle.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass
from typing import Any

from rtloop.errors import PortValueError

HELP = "switch a running task to another of its controllers at one release"

LEAD_S = 0.2
"""How far ahead of now a switch is placed when no --at-cycle is given: the write must reach the
task before that release, whatever this process is kept waiting by the machine."""


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


@dataclass(frozen=True)
class SwitchPort:
    task: str
    port: str
    controllers: tuple[str, ...]
    period_ns: int


def run(args: argparse.Namespace) -> int:
    from rtloop.ipc.ports import connect_app

    app = connect_app(args.app, owner_uid=args.user)
    pairs = parse_changes(args.changes, promote=args.promote or args.stop_shadow)
    ports = switch_ports(app.ports)
    chosen: list[tuple[SwitchPort, str | None]] = []
    for task, controller in pairs:  # every name checked before anything is written: all or none
        if task not in ports:
            known = sorted(ports) or "none"
            raise PortValueError(f"app {app.name!r}: task {task!r} has no controllers to switch "
                                 f"(tasks with [tasks.NAME.controllers]: {known})")
        if controller is not None and controller not in ports[task].controllers:
            raise PortValueError(f"task {task!r} has no controller {controller!r}; "
                                 f"its controllers are {list(ports[task].controllers)}")
        chosen.append((ports[task], controller))
    t0_ns = app.epoch_ns()
    if not t0_ns:
        raise PortValueError(f"app {app.name!r} has not started its tasks yet; switch once it runs")
    first = chosen[0][0]
    now_ns = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
    if args.at_cycle is not None:
        at_ns = t0_ns + args.at_cycle * first.period_ns
        if at_ns <= now_ns:
            now_cycle = (now_ns - t0_ns) // first.period_ns
            raise PortValueError(f"--at-cycle {args.at_cycle}: task {first.task!r} is at cycle {now_cycle} already; "
                                 "give a release still to come")
    else:
        at_ns = now_ns + int(LEAD_S * 1e9)
    lines = []
    for port, controller in chosen:
        at_cycle = math.ceil((at_ns - t0_ns) / port.period_ns)
        values, said = request(app.peek(port.port), port, controller, at_cycle, args)
        app.write(port.port, values)
        lines.append(f"{port.task}: {said}")
    late = [port.task for port, _ in chosen
            if time.clock_gettime_ns(time.CLOCK_MONOTONIC) > t0_ns + math.ceil((at_ns - t0_ns) / port.period_ns)
            * port.period_ns]
    print("\n".join(lines))
    if late:
        print(f"rtloop switch: the request reached {', '.join(late)} after the release named: it took effect at "
              "the first release after it (summary.json's switches say which)")
    return 0


def request(current: Any, port: SwitchPort, controller: str | None, at_cycle: int,
            args: argparse.Namespace) -> tuple[list[float], str]:
    """The switch port's four values for this request (no new code: 0), and the answer to print."""
    active_request, shadow = float(current[0]), float(current[2])
    when = f"at cycle {at_cycle} (t = {at_cycle * port.period_ns / 1e9:.6f} s)"
    if args.stop_shadow:
        return [active_request, float(at_cycle), -1.0, 0.0], f"shadow controller stopped {when}"
    if args.promote:
        if shadow < 0 and controller is None:
            raise PortValueError(f"task {port.task!r} runs no shadow controller to promote; "
                                 f"start one with: rtloop switch APP {port.task} CONTROLLER --shadow")
        index = port.controllers.index(controller) if controller is not None else int(shadow)
        return [float(index), float(at_cycle), float(index), 0.0], f"{port.controllers[index]} promoted {when}"
    assert controller is not None
    wanted = float(port.controllers.index(controller))
    if args.shadow:
        return [active_request, float(at_cycle), wanted, 0.0], f"{controller} runs in shadow from {when}"
    return [wanted, float(at_cycle), shadow, 0.0], f"{controller} active {when}"


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


def switch_ports(ports: dict[str, dict[str, Any]]) -> dict[str, SwitchPort]:
    """The running app's switch ports, by task (from the registry)."""
    found: dict[str, SwitchPort] = {}
    for name, info in ports.items():
        names, task = info.get("controllers"), info.get("switch_task")
        if isinstance(names, list) and isinstance(task, str) and all(isinstance(n, str) for n in names):
            found[task] = SwitchPort(task, name, tuple(names), int(info["period_ns"]))
    return found
