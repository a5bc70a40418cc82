"""Switching a running task's controller from non-real-time code (what ``rtloop switch`` does).

    from rtloop.ipc.ports import connect_app
    from rtloop.ipc.switch_requests import switch
    app = connect_app("jiwy_switch")
    print(switch(app, {"controller": "soft"}))               # about 0.2 s from now, at one release
    switch(app, {"controller": "lqr"}, mode="shadow")         # run lqr beside the active one
    switch(app, {"controller": None}, mode="promote")         # the shadow becomes the active one

A request is a write to the task's switch port (``<task>_switch``), so it is logged like any
port write and ``rtloop replay`` reproduces it. Every name is checked before anything is
written: a request naming a task or controller that does not exist changes nothing.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from rtloop.errors import PortValueError
from rtloop.ipc.ports import RunningApp

LEAD_S = 0.2
"""How far ahead of now a switch is placed when no cycle is given: the write must reach the task
before that release, whatever this process is kept waiting by the machine."""
Mode = Literal["active", "shadow", "promote", "stop_shadow"]


@dataclass(frozen=True)
class SwitchPort:
    task: str
    port: str
    controllers: tuple[str, ...]
    period_ns: int


@dataclass(frozen=True)
class SwitchAnswer:
    task: str
    at_cycle: int
    """The release from which the request holds (the first one the task runs from there)."""
    said: str
    late: bool
    """The write reached the task after that release: it acted at the first release after the write."""


def switch_ports(ports: Mapping[str, Mapping[str, Any]]) -> dict[str, SwitchPort]:
    """The running app's switch ports, by task (from its registry)."""
    found: dict[str, SwitchPort] = {}
    for name, info in ports.items():
        names, task = info.get("controllers"), info.get("switch_task")
        if isinstance(names, list) and isinstance(task, str) and all(isinstance(n, str) for n in names):
            found[task] = SwitchPort(task, name, tuple(names), int(info["period_ns"]))
    return found


def switch_port_of(app: RunningApp, task: str, controller: str | None, verb: str) -> SwitchPort:
    """``task``'s switch port, checked to have ``controller`` (None: any), or why not (``verb``: what for)."""
    ports = switch_ports(app.ports)
    if task not in ports:
        raise PortValueError(f"app {app.name!r}: task {task!r} has no controllers to {verb} "
                             f"(tasks with [tasks.NAME.controllers]: {sorted(ports) or 'none'})")
    if controller is not None and controller not in ports[task].controllers:
        raise PortValueError(f"task {task!r} has no controller {controller!r}; "
                             f"its controllers are {list(ports[task].controllers)}")
    return ports[task]


def release_at(app: RunningApp, port: SwitchPort, at_cycle: int | None, lead_s: float, verb: str) -> tuple[int, int]:
    """(T0, the instant a request holds from): ``at_cycle`` of ``port``'s task, or ``lead_s`` from now."""
    t0_ns = app.epoch_ns()
    if not t0_ns:
        raise PortValueError(f"app {app.name!r} has not started its tasks yet; {verb} once it runs")
    now_ns = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
    if at_cycle is None:
        return t0_ns, now_ns + int(lead_s * 1e9)
    at_ns = t0_ns + at_cycle * port.period_ns
    if at_ns <= now_ns:
        raise PortValueError(f"at cycle {at_cycle}: task {port.task!r} is at cycle "
                             f"{(now_ns - t0_ns) // port.period_ns} already; give a release still to come")
    return t0_ns, at_ns


def switch(app: RunningApp, changes: Mapping[str, str | None], *, at_cycle: int | None = None,
           mode: Mode = "active", lead_s: float = LEAD_S) -> list[SwitchAnswer]:
    """Ask each task of ``changes`` for its controller (``None``: with ``promote``, the task's shadow)
    from one release: ``at_cycle`` (in the first task's periods) or about ``lead_s`` from now."""
    if not changes:
        raise PortValueError("switch: name at least one task and its controller")
    chosen: list[tuple[SwitchPort, str | None]] = []
    for task, controller in changes.items():  # every name checked before anything is written: all or none
        port = switch_port_of(app, task, controller, "switch")
        if controller is None and mode not in ("promote", "stop_shadow"):
            raise PortValueError(f"switch: name the controller for task {task!r}")
        chosen.append((port, controller))
    t0_ns, at_ns = release_at(app, chosen[0][0], at_cycle, lead_s, "switch")
    requests = [(port, *_request(app.peek(port.port), port, controller,
                                 release_cycle(at_ns - t0_ns, port, at_cycle), mode))
                for port, controller in chosen]  # all built (and refused) before the first write
    answers = []
    for port, values, said in requests:
        app.write(port.port, values)
        cycle = int(values[1])
        late = time.clock_gettime_ns(time.CLOCK_MONOTONIC) > t0_ns + cycle * port.period_ns
        answers.append(SwitchAnswer(port.task, cycle, said, late))
    return answers


MAX_SWITCH_CYCLE = 1 << 53
"""The last cycle a switch can name: the switch port holds it as a double, exact up to 2**53."""


def release_cycle(since_t0_ns: int, port: SwitchPort, asked: int | None) -> int:
    """The first release of ``port``'s task at or after ``since_t0_ns``; past the port's range (an
    ``--at-cycle`` of 1e29) refused naming the option, not the port's internal range."""
    cycle = -(-since_t0_ns // port.period_ns)  # integers: a float division loses cycles past 2**53
    if cycle > MAX_SWITCH_CYCLE:
        raise PortValueError(f"at cycle {asked}: task {port.task!r} would reach it at its cycle {cycle}, past the "
                             f"last a switch can name ({MAX_SWITCH_CYCLE}, 2**53)")
    return cycle


def _request(current: Any, port: SwitchPort, controller: str | None, at_cycle: int,
             mode: Mode) -> tuple[list[float], str]:
    """The switch port's four values for this request (no new code: 0), and the answer to print."""
    active_request, shadow = float(current[0]), float(current[2])
    release = f"cycle {at_cycle} (t = {at_cycle * port.period_ns / 1e9:.6f} s)"
    when = f"at {release}"
    if mode == "stop_shadow":
        if shadow < 0:
            raise PortValueError(f"task {port.task!r} runs no shadow controller to stop")
        return [active_request, float(at_cycle), -1.0, 0.0], f"shadow controller stopped {when}"
    if mode == "promote":
        if shadow < 0 and controller is None:
            raise PortValueError(f"task {port.task!r} runs no shadow controller to promote; "
                                 f"start one with: rtloop switch APP {port.task} CONTROLLER --shadow")
        index = port.controllers.index(controller) if controller is not None else int(shadow)
        return [float(index), float(at_cycle), float(index), 0.0], f"{port.controllers[index]} promoted {when}"
    assert controller is not None
    wanted = float(port.controllers.index(controller))
    if mode == "shadow":
        if wanted == active_request:  # the task ignores it; the answer said it ran
            raise PortValueError(f"{controller} is the active controller of task {port.task!r} (or the one it was "
                                 "asked for): a shadow runs another beside it")
        return [active_request, float(at_cycle), wanted, 0.0], f"{controller} runs in shadow from {release}"
    return [wanted, float(at_cycle), shadow, 0.0], f"{controller} active {when}"
