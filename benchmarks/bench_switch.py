"""JIWY's controller switched live and back, then its edited code reloaded: misses, jumps, replay, the reload's cost.

One real run of ``examples/jiwy/jiwy_switch.toml`` (the app file and ``jiwy_models.py`` copied into a
folder of the benchmark's own, so the edit touches the copy), its pan and tilt setpoints a slow sine, so
that the steering moves every cycle and a bump would stand out against a known normal change:

1. ``pid`` → ``soft`` at one release, then ``soft`` → ``pid`` at another (both named about 3 s ahead,
   through ``rtloop.ipc.switch_requests.switch``: what ``rtloop switch`` calls);
2. ``--reloads N`` times (1 by default, 0 with ``--no-reload``): the copy of ``jiwy_models.py`` edited
   while it runs (the lead filter of the PID made k + 1 times as slow at reload k, so each reload brings
   other code) and ``rtloop reload APP controller pid --at-cycle N`` (its code, run in this process);
3. the run stopped by SIGTERM, then ``rtloop replay`` of the whole run.

Printed: per change, the cycle asked and the one summary.json lists; the deadline misses and skipped
releases of both tasks within ±20 cycles; the steering's jump at the change (the outgoing controller's
last output to the incoming one's first) next to the normal per-cycle change (p99 over the run, and the
largest within ±20 cycles); for each reload, the loop's wake-up latency and execution time while the
reload thread prepared the new code (from its own timeline: the request taken to the code ready; its
phases; how often and how long it left the loop its slack, code_reload.SlackGate) next to as many cycles
just before the request, and the swap's own cycle; the replay's verdict; and one row summing the reloads,
ready for BENCHMARKS.md.

Usage (as root, for a real-time run; about 25 s, 1.5 s more per reload)::

    python benchmarks/bench_switch.py [--reloads N | --no-reload] [--trace] [--json PATH]

``--trace`` (root, a kernel with tracefs): the controller's loop thread's system calls in the kernel's
trace from each reload's request to 100 cycles after its hand-over, to count the wake-ups that waited
for the interpreter's lock (a futex wait between waking and sleeping again; benchmarks/_lock_wait_trace.py).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import (
    add_output_options,
    closing_sections,
    load_timing_csv,
    machine_facts,
    markdown_table,
    print_and_save,
    result_head,
)
from _lock_wait_trace import LockWaitTrace, waits_within

import rtloop
from rtloop.code_reload import code_id_of
from rtloop.ipc.ports import RunningApp, running_apps
from rtloop.ipc.status import STATUS_WORDS, StatusWord, WordBlock
from rtloop.ipc.switch_requests import switch

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "jiwy"
PERIOD_NS = 1_000_000  # the example's period, both tasks
NEAR_CYCLES = 20
"""The must-show's window: no miss within ±20 cycles of a change."""
AHEAD_CYCLES = 3000
"""How far ahead a change is named: the request (a CLI's start, on a loaded machine) must come before it."""
AFTER_CYCLES = 1500
"""Cycles run after the last change before the run is stopped."""
FILTER_EDIT = ("(c.beta * c.tau_d_s)", "({factor:.1f} * c.beta * c.tau_d_s)")
"""The edit made to the running PID's module for reload k (1, 2, ...): its lead filter k + 1 times as slow
(its output equation, which ``take_over`` solves, is unchanged, so the hand-over stays bumpless; each
reload's code differs from the last)."""
RELOAD_AHEAD_CYCLES = 1500
"""How far ahead a reload after the first is named (the command runs in this process: 0.2-0.3 s)."""


def sine_profile(path: Path, seconds: float) -> None:
    """Pan and tilt setpoints: a 0.3 rad and 0.2 rad sine of 4 s, in 5 ms steps."""
    t_s = np.arange(0.0, seconds, 0.005)
    with open(path, "w") as file:
        file.write("t_s,pan,tilt\n")
        for t in t_s.tolist():
            file.write(f"{t:.3f},{0.3 * math.sin(2 * math.pi * t / 4):.9f},{0.2 * math.sin(2 * math.pi * t / 4):.9f}\n")


def make_app(folder: Path, name: str, cpu: str) -> Path:
    text = (EXAMPLE / "jiwy_switch.toml").read_text().replace('name = "jiwy_switch"', f'name = "{name}"')
    if cpu != "1":
        text = text.replace("cpu = 1", "" if cpu == "none" else f"cpu = {int(cpu)}")
    app_file = folder / "jiwy_switch.toml"
    app_file.write_text(text)
    shutil.copyfile(EXAMPLE / "jiwy_models.py", folder / "jiwy_models.py")
    return app_file


def wait_for_app(name: str, process: subprocess.Popen[str], timeout_s: float = 60.0) -> RunningApp:
    """The app ``rtloop run`` (``process``) started, or its own error if it ended first."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for app in running_apps():
            if app.name == name and app.pid == process.pid:
                return app
        if process.poll() is not None:
            raise SystemExit(f"bench_switch: rtloop run ended (exit {process.returncode}) before the app ran: "
                             f"{process.communicate()[1].strip()}")
        time.sleep(0.05)
    raise SystemExit(f"bench_switch: app {name!r} did not start within {timeout_s:g} s")


def cycles_done(app: RunningApp, task: str) -> int:
    status = WordBlock(app.segment(app.registry["tasks"][task]), 0, STATUS_WORDS)
    return int(status[StatusWord.CYCLE]) + 1 if status[StatusWord.EXEC_LAST_NS] > 0 else 0


def wait_for_cycle(app: RunningApp, task: str, cycle: int, process: subprocess.Popen[str],
                   timeout_s: float = 120.0) -> int:
    deadline = time.monotonic() + timeout_s
    while (done := cycles_done(app, task)) < cycle:
        if process.poll() is not None:
            raise SystemExit(f"bench_switch: the run ended early (exit {process.returncode}): "
                             f"{process.communicate()[1]}")
        if time.monotonic() > deadline:
            raise SystemExit(f"bench_switch: task {task!r} reached cycle {done}, not {cycle}, in {timeout_s:g} s")
        time.sleep(0.02)
    return done


def rtloop_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rtloop.cli", *args], capture_output=True, text=True, timeout=300)


def reload_in_process(name: str, at_cycle: int) -> str:
    """``rtloop reload APP controller pid --at-cycle N``, run in this process (the command's own code: a
    new interpreter's start took over 3 s on a loaded machine, past the release it named); its answer."""
    from rtloop.cli import reload as reload_command
    from rtloop.errors import PortValueError

    arguments = argparse.Namespace(app=name, task="controller", controller="pid", file=None, at_cycle=at_cycle,
                                   user=None)
    said = io.StringIO()
    try:
        with contextlib.redirect_stdout(said):
            reload_command.run(arguments)
    except PortValueError as error:
        raise SystemExit(f"bench_switch: rtloop reload refused: {error}") from None
    return said.getvalue().strip()


def drive_the_run(folder: Path, app_file: Path, profile: Path, run_dir: Path, name: str,
                  reloads: int, tracer: LockWaitTrace | None = None) -> dict[str, Any]:
    """The run with its changes; returns what was asked (cycles, the reloads' codes and answers). ``tracer``:
    the controller's loop thread traced from each reload's request to 100 cycles after its hand-over (--trace)."""
    asked: dict[str, Any] = {"changes": []}
    process = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--out", str(run_dir),
                                "-q", "--feed", f"setpoint={profile}"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        app = wait_for_app(name, process)
        done = wait_for_cycle(app, "controller", 1000, process)
        for target in ("soft", "pid"):
            [answer] = switch(app, {"controller": target}, at_cycle=done + AHEAD_CYCLES)
            asked["changes"].append({"what": f"switch to {target}", "asked_cycle": answer.at_cycle})
            done = wait_for_cycle(app, "controller", answer.at_cycle + 100, process)
        module = folder / "jiwy_models.py"
        original = module.read_text()
        if reloads and original.count(FILTER_EDIT[0]) != 1:
            raise SystemExit(f"bench_switch: {module} no longer has {FILTER_EDIT[0]!r} once: update FILTER_EDIT")
        asked["reloads"] = []
        if tracer is not None:
            tracer.arm(app.task_pids()["controller"])  # its loop runs in its main thread
        for k in range(1, reloads + 1):
            edited = original.replace(FILTER_EDIT[0], FILTER_EDIT[1].format(factor=k + 1.0))
            module.write_text(edited)
            at_cycle = cycles_done(app, "controller") + (AHEAD_CYCLES if k == 1 else RELOAD_AHEAD_CYCLES)
            started = time.monotonic()
            if tracer is not None:
                tracer.switch(True)
            try:  # traced from the request to 100 cycles after the hand-over
                answer = reload_in_process(name, at_cycle)  # it returns once the task has prepared the code
                asked["reloads"].append({"asked_cycle": at_cycle, "code": f"{code_id_of(edited.encode()):012x}",
                                         "answer": answer, "command_s": time.monotonic() - started})
                asked["changes"].append({"what": f"reload {k} of pid (edited)", "asked_cycle": at_cycle})
                done = wait_for_cycle(app, "controller", at_cycle + 100, process)
            finally:
                if tracer is not None:
                    tracer.switch(False)
        wait_for_cycle(app, "controller", asked["changes"][-1]["asked_cycle"] + AFTER_CYCLES, process)
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)  # an orderly stop: summary.json, every row written
        _out, err = process.communicate(timeout=120)
    if process.returncode != 0:
        raise SystemExit(f"bench_switch: rtloop run ended with exit {process.returncode}: {err.strip()}")
    return asked


def near_misses(timing: dict[str, np.ndarray], cycle: int) -> dict[str, dict[str, int]]:
    """Per task: deadline misses (a cycle that ended after the next release) and releases skipped,
    among the cycles within ±NEAR_CYCLES of ``cycle``."""
    out = {}
    for task, records in timing.items():
        window = records[(records[:, 0] >= cycle - NEAR_CYCLES) & (records[:, 0] <= cycle + NEAR_CYCLES)]
        misses = int(np.count_nonzero(window[:, 3] > window[:, 1] + PERIOD_NS))
        skipped = 2 * NEAR_CYCLES + 1 - len(window)
        out[task] = {"misses": misses, "skipped": skipped}
    return out


def jumps(signals: Any, cycles: list[int]) -> dict[str, Any]:
    """The steering's change at each change's first output, next to its normal per-cycle change."""
    t_ns = np.round(np.asarray(signals.t_s) * 1e9).astype(np.int64)
    one_period = np.diff(t_ns) == PERIOD_NS  # changes across a skipped release are not one cycle's
    change_rows = {int(np.searchsorted(t_ns, (cycle + 1) * PERIOD_NS)) for cycle in cycles}
    out: dict[str, Any] = {}
    for column in ("controller.SteeringPan", "controller.SteeringTilt"):
        values = np.asarray(signals[column])
        changes = np.abs(np.diff(values))
        normal = one_period & ~np.isnan(changes)
        for row in change_rows:
            normal[max(0, row - 1)] = False  # changes[row - 1]: from the last old output to the first new one
        per_change = []
        for cycle in cycles:
            row = int(np.searchsorted(t_ns, (cycle + 1) * PERIOD_NS))
            around = slice(max(0, row - 1 - NEAR_CYCLES), row - 1 + NEAR_CYCLES + 1)
            local = changes[around][normal[around]]
            per_change.append({"cycle": cycle, "row_t_s": float(t_ns[row]) / 1e9, "jump": float(changes[row - 1]),
                               "near_max": float(local.max()) if local.size else math.nan})
        out[column] = {"normal_p99": float(np.percentile(changes[normal], 99)),
                       "normal_p50": float(np.percentile(changes[normal], 50)), "changes": per_change}
    return out


def reload_cost(run_dir: Path, timing: dict[str, np.ndarray], reload: dict[str, Any]) -> dict[str, Any] | None:
    """The loop's timing while the reload thread prepared one reload's code (from the release that took the
    request to the moment the code was ready, the thread's own timeline), next to as many cycles before it."""
    taken = None
    with open(run_dir / "inputs.csv") as file:
        for row in csv.DictReader(file):
            values = [float(v) for v in row["values"].split()]
            if row["port"] == "controller_switch" and len(values) == 4 and values[3] and \
                    int(values[1]) == reload["asked_cycle"] and taken is None:
                taken = int(row["cycle"])
    try:
        answer = json.loads((run_dir / "code" / f"pid-{reload['code']}.result.json").read_text())
    except (OSError, ValueError):
        return None
    if taken is None or not answer.get("accepted"):
        return None
    controller = timing["controller"]
    t0_ns = int(controller[0, 1] - controller[0, 0] * PERIOD_NS)
    timeline = answer.get("timeline_ns", {})
    asked_ns = int(timeline.get("asked", t0_ns + taken * PERIOD_NS))
    ready_ns = int(answer["ready_ns"])
    first_cycle = (asked_ns - t0_ns) // PERIOD_NS + 1  # the first release after the thread took the request
    ready_cycle = math.ceil((ready_ns - t0_ns) / PERIOD_NS)
    out: dict[str, Any] = {"request_taken_cycle": taken, "first_cycle": first_cycle, "ready_cycle": ready_cycle,
                           "asked_ns": asked_ns, "ready_ns": ready_ns,
                           "preparation_ms": (ready_ns - asked_ns) / 1e6,
                           "phases_ms": _phases_ms(timeline),
                           "slack_waits": answer.get("slack_waits"),
                           "slack_waited_ms": answer.get("slack_waited_ns", 0) / 1e6,
                           "dry_step_us": answer.get("dry_step_ns", 0) / 1e3, "tasks": {}}
    span = max(ready_cycle - first_cycle + 1, 1)
    for task, records in timing.items():
        cycles = records[:, 0]
        during = records[(cycles >= first_cycle) & (cycles <= ready_cycle)]
        before = records[(cycles >= taken - span - 50) & (cycles < taken - 50)]  # clear of the request's own write
        swap = records[cycles == (reload.get("listed_cycle") or reload["asked_cycle"])]
        out["tasks"][task] = {
            "cycles_during": len(during), "skipped_during": span - len(during),
            "latency_us_during": _us(during[:, 2] - during[:, 1]),
            "latency_us_before": _us(before[:, 2] - before[:, 1]),
            "exec_us_during": _us(during[:, 3] - during[:, 2]), "exec_us_before": _us(before[:, 3] - before[:, 2]),
            "misses_during": int(np.count_nonzero(during[:, 3] > during[:, 1] + PERIOD_NS)),
            "swap_exec_us": float((swap[0, 3] - swap[0, 2]) / 1e3) if len(swap) else math.nan,
        }
    return out


def _phases_ms(timeline: dict[str, int]) -> dict[str, float]:
    """Each phase's duration from the reload thread's timeline (code_reload.PHASES, in order)."""
    out, last = {}, None
    for phase, at_ns in timeline.items():
        if last is not None and at_ns and last:
            out[phase] = (at_ns - last) / 1e6
        last = at_ns
    return out


def _us(values_ns: np.ndarray) -> dict[str, float]:
    if not len(values_ns):
        return {"p50": math.nan, "max": math.nan}
    return {"p50": float(np.percentile(values_ns, 50)) / 1e3, "max": float(values_ns.max()) / 1e3}


def replay_run(run_dir: Path, out: Path) -> dict[str, Any]:
    started = time.monotonic()
    replayed = rtloop_cli("replay", str(run_dir), "--out", str(out))
    seconds = time.monotonic() - started
    run_switches = json.loads((run_dir / "summary.json").read_text()).get("switches")
    try:
        replay_switches = json.loads((out / "summary.json").read_text()).get("switches")
    except (OSError, ValueError):
        replay_switches = None
    lines = [line for line in (replayed.stdout + replayed.stderr).splitlines() if line.strip()]
    return {"exit": replayed.returncode, "bit_for_bit": replayed.returncode == 0 and "bit for bit" in replayed.stdout,
            "switches_equal": run_switches == replay_switches, "seconds": seconds,
            "said": next((line for line in lines if "bit for bit" in line or "differ" in line),
                         lines[-1] if lines else "")}


def report(result: dict[str, Any]) -> str:
    changes = result["changes"]
    rows = []
    for change in changes:
        near = change["near"]
        rows.append([change["what"], change["asked_cycle"], change.get("listed_cycle", "not listed"),
                     change.get("transfer", ""),
                     " / ".join(f"{task} {near[task]['misses']}" for task in sorted(near)),
                     " / ".join(f"{task} {near[task]['skipped']}" for task in sorted(near))])
    parts = [f"## Switching JIWY's controller live ({result['machine']['date']})",
             f"run: {result['run']['cycles']} cycles of the controller, real-time: {result['run']['rt']}, "
             f"deadline misses in the whole run: {result['run']['deadline_misses']}",
             markdown_table(["change", "asked at cycle", "summary.json cycle", "transfer",
                             f"misses ±{NEAR_CYCLES} cycles", f"skipped ±{NEAR_CYCLES} cycles"], rows)]
    jump_rows = []
    for column, figures in result["jumps"].items():
        for change, figure in zip(changes, figures["changes"], strict=True):
            jump_rows.append([column.split(".")[1], change["what"], f"{figure['jump']:.2e}",
                              f"{figure['near_max']:.2e}", f"{figures['normal_p99']:.2e}",
                              figure["jump"] <= figures["normal_p99"]])
    parts += ["### The output's jump at each change (the last old output to the first new one)",
              markdown_table(["output", "change", "jump at the change", f"largest change ±{NEAR_CYCLES} cycles",
                              "normal change p99 (run)", "jump ≤ p99"], jump_rows)]
    costs = [(k, cost) for k, cost in enumerate(result.get("reload_costs") or [], 1) if cost]
    if costs:
        cost_rows = []
        for k, cost in costs:
            waits = f"{cost['slack_waits']} / {cost['slack_waited_ms']:.1f}"
            for task, figures in cost["tasks"].items():
                cost_rows.append([k, task, f"{cost['preparation_ms']:.1f}", waits if task == "controller" else "",
                                  f"{figures['cycles_during']} ({figures['skipped_during']})",
                                  _p50_max(figures["latency_us_before"]), _p50_max(figures["latency_us_during"]),
                                  _p50_max(figures["exec_us_before"]), _p50_max(figures["exec_us_during"]),
                                  figures["misses_during"], f"{figures['swap_exec_us']:.1f}"])
        parts += ["### The reloads' cost on the loop (the reload thread's preparation, from its own timeline; "
                  "the reference: as many cycles just before the request)",
                  markdown_table(["reload", "task", "prepared in ms", "slack waits / ms",
                                  "cycles while preparing (skipped)", "wake-up µs before p50 / max",
                                  "wake-up µs while preparing p50 / max", "exec µs before p50 / max",
                                  "exec µs while preparing p50 / max", "misses while preparing",
                                  "exec µs of the swap's cycle"], cost_rows),
                  "Phases (ms): " + "; ".join(
                      f"reload {k}: " + ", ".join(f"{phase} {ms:.2f}" for phase, ms in cost["phases_ms"].items())
                      for k, cost in costs),
                  "`rtloop reload` said: " + " | ".join(r["answer"] for r in result["reloads"])]
        lock = result.get("lock_waits")
        if lock:
            outside = lock["traced_outside"]
            parts += ["### The loop's wake-ups while each reload was prepared and around its hand-over, in the "
                      "kernel's trace (did it wait "
                      "on the interpreter's lock between waking and sleeping again?)",
                      markdown_table(["reload", "wake-ups", "that waited for the lock", "longest wait µs"],
                                     [[f"{k}: preparing", figures["wake_ups"], figures["waited"],
                                       f"{figures['longest_us']:.1f}"]
                                      for k, figures in enumerate(lock["per_reload"], 1)]
                                     + [[f"{k}: hand-over ±{NEAR_CYCLES} cycles", figures["wake_ups"],
                                         figures["waited"], f"{figures['longest_us']:.1f}"]
                                        for k, figures in enumerate(lock["hand_overs"], 1)]
                                     + [["traced, neither", outside["wake_ups"], outside["waited"],
                                         f"{outside['longest_us']:.1f}"]]),
                      "As it began such a wait, the CPU went to (kernel prio: 98 is SCHED_FIFO 1, the reload "
                      "thread's; 120 SCHED_OTHER): " + (", ".join(f"{who} ×{n}" for who, n in sorted(
                          lock["cpu_went_to"].items(), key=lambda item: -item[1])) or "no wait")]
        parts += ["### Rows for BENCHMARKS.md",
                  markdown_table(["date (UTC)", "load at start", "reloads", "prepared in ms",
                                  "controller wake-up µs before: max", "while preparing: p50 / max",
                                  "plant (own process) while preparing: max", "controller misses while preparing",
                                  f"misses and skipped ±{NEAR_CYCLES} cycles of each reload",
                                  "wake-ups that waited for the lock (--trace)"],
                                 [benchmarks_row(result, costs)])]
    replay = result["replay"]
    parts += ["### Replay of the whole run",
              f"bit for bit: {replay['bit_for_bit']}; switches listed alike: {replay['switches_equal']}; "
              f"{replay['seconds']:.1f} s; it said: {replay['said']}",
              "summary.json switches: " + json.dumps(result["switches"])]
    return "\n\n".join(parts)


def _p50_max(figures: dict[str, float]) -> str:
    return f"{figures['p50']:.1f} / {figures['max']:.1f}"


def benchmarks_row(result: dict[str, Any], costs: list[tuple[int, dict[str, Any]]]) -> list[Any]:
    """One row summing every reload of the run: the figures the switch section of BENCHMARKS.md tabulates."""
    controller = [cost["tasks"]["controller"] for _k, cost in costs]
    during_p50 = max(figures["latency_us_during"]["p50"] for figures in controller)
    reload_changes = [change for change in result["changes"] if change["what"].startswith("reload")]
    near = sum(figures["misses"] + figures["skipped"] for change in reload_changes
               for figures in change["near"].values())
    return [result["machine"]["date"][:16].replace("T", " "), " ".join(result["machine"]["loadavg_at_start"]),
            len(costs), " / ".join(f"{cost['preparation_ms']:.1f}" for _k, cost in costs),
            f"{max(figures['latency_us_before']['max'] for figures in controller):.0f}",
            f"{during_p50:.0f} / {max(figures['latency_us_during']['max'] for figures in controller):.0f}",
            f"{max(cost['tasks']['plant']['latency_us_during']['max'] for _k, cost in costs):.0f}",
            sum(figures["misses_during"] for figures in controller), near, _lock_waits_cell(result)]


def _lock_waits_cell(result: dict[str, Any]) -> str:
    lock = result.get("lock_waits")
    if not lock:
        return "not traced"
    per_reload = lock["per_reload"]
    waited, woke = sum(f["waited"] for f in per_reload), sum(f["wake_ups"] for f in per_reload)
    return f"{waited} of {woke} (longest {max(f['longest_us'] for f in per_reload):.0f} µs)"


def targets(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The must-show's figures (issue 34): no miss near a change, no jump beyond a normal change, replay equal."""
    changes = result["changes"]
    near = sum(figures["misses"] + figures["skipped"] for change in changes for figures in change["near"].values())
    worst = max(figure["jump"] / figures["normal_p99"] for figures in result["jumps"].values()
                for figure in figures["changes"])
    listed = all(change.get("listed_cycle") == change.get("first_cycle_run") for change in changes)
    replay = result["replay"]
    replay_equal = bool(replay["bit_for_bit"] and replay["switches_equal"])
    found = [
        {"target": f"0 deadline misses or skipped releases within ±{NEAR_CYCLES} cycles of each change "
                   "(a quiet run)", "measured": str(near), "met": near == 0},
        {"target": "each change's jump ≤ the normal per-cycle change (p99)",
         "measured": f"largest jump / p99 = {worst:.2e}", "met": worst <= 1.0},
        {"target": "summary.json lists each change at the release asked (or the first one run from it)",
         "measured": str([change.get("listed_cycle") for change in changes]), "met": listed},
        {"target": "rtloop replay bit for bit over the whole run",
         "measured": "equal, switches alike" if replay_equal else replay["said"], "met": replay_equal},
    ]
    costs = [cost for cost in result.get("reload_costs") or [] if cost]
    if result.get("reloads"):
        misses = sum(cost["tasks"]["controller"]["misses_during"] for cost in costs)
        prepared = sum(cost["preparation_ms"] for cost in costs)
        found.append({"target": "each reload's preparation: no deadline miss of the controller",
                      "measured": f"{misses} in {len(costs)} of {len(result['reloads'])} reloads measured "
                                  f"({prepared:.0f} ms of preparation)",
                      "met": misses == 0 and len(costs) == len(result["reloads"])})
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reloads", type=int, default=1, metavar="N",
                        help="reload the edited module N times after the switches, each with other code (default 1)")
    parser.add_argument("--no-reload", action="store_true", help="the two switches only (--reloads 0)")
    parser.add_argument("--trace", action="store_true",
                        help="root: trace the controller's loop thread in the kernel from each reload's request to "
                             "its hand-over (did a wake-up wait for the interpreter's lock?)")
    parser.add_argument("--cpu", default="1",
                        help="the CPU both tasks are pinned to (the example's: 1); none: unpinned")
    parser.add_argument("--keep", metavar="DIR", help="keep the run, its replay and the app's folder in DIR")
    add_output_options(parser)
    args = parser.parse_args(argv)
    if args.no_reload:
        args.reloads = 0
    if not 0 <= args.reloads <= 20:
        parser.error(f"--reloads {args.reloads}: give 0 to 20")
    started = time.monotonic()
    facts = machine_facts()
    folder = Path(tempfile.mkdtemp(prefix="bench_switch_")) if not args.keep else Path(args.keep)
    if args.keep and folder.exists() and any(folder.iterdir()):
        parser.error(f"--keep {folder}: not empty; name a new folder")
    folder.mkdir(parents=True, exist_ok=True)
    try:
        name = f"bench_switch_{os.getpid()}"
        app_file = make_app(folder, name, args.cpu)
        profile = folder / "sine.csv"
        sine_profile(profile, 60.0)
        run_dir = folder / "run"
        tracer = LockWaitTrace() if args.trace and args.reloads else None
        try:
            asked = drive_the_run(folder, app_file, profile, run_dir, name, args.reloads, tracer)
            wake_ups = tracer.wake_ups() if tracer is not None else None
            held_by = tracer.held_by if tracer is not None else {}
        finally:
            if tracer is not None:
                tracer.close()
        summary = json.loads((run_dir / "summary.json").read_text())
        switches = summary.get("switches") or []
        timing = load_timing_csv(run_dir / "timing.csv")
        ran = timing["controller"][:, 0]
        changes = asked["changes"]
        for change, listed in zip(changes, switches, strict=False):
            change["listed_cycle"], change["transfer"] = listed["cycle"], listed["transfer"]
        for change in changes:
            first_run = ran[ran >= change["asked_cycle"]]
            change["first_cycle_run"] = int(first_run[0]) if len(first_run) else None
            change["near"] = near_misses(timing, change.get("listed_cycle", change["asked_cycle"]))
        signals = rtloop.load(run_dir).signals
        result = result_head("bench_switch", args, facts, started)
        task = summary["tasks"]["controller"]
        result.update({
            "run": {"cycles": task["cycles"], "rt": task["rt"],
                    "deadline_misses": {name_: t["deadline_misses"] for name_, t in summary["tasks"].items()}},
            "changes": changes, "switches": switches,
            "jumps": jumps(signals, [c.get("listed_cycle", c["asked_cycle"]) for c in changes]),
            "reloads": asked["reloads"],
            "reload_costs": [reload_cost(run_dir, timing, {**reload, "listed_cycle": change.get("listed_cycle")})
                             for reload, change in zip(asked["reloads"], changes[2:], strict=False)],
            "replay": replay_run(run_dir, folder / "replay"),
        })
        if wake_ups is not None:
            windows = [(cost["asked_ns"], cost["ready_ns"]) if cost else (0, -1) for cost in result["reload_costs"]]
            t0_ns = int(timing["controller"][0, 1] - timing["controller"][0, 0] * PERIOD_NS)
            hand_overs = [(t0_ns + (cycle - NEAR_CYCLES) * PERIOD_NS, t0_ns + (cycle + NEAR_CYCLES + 1) * PERIOD_NS)
                          for cycle in (change.get("listed_cycle") or change["asked_cycle"] for change in changes[2:])]
            windows_ = windows + hand_overs
            result["lock_waits"] = {"per_reload": waits_within(wake_ups, windows),
                                    "hand_overs": waits_within(wake_ups, hand_overs),
                                    "traced_outside": waits_within(
                                        [w for w in wake_ups if not any(a <= w[0] <= b for a, b in windows_)],
                                        [(0, 2**63)])[0],
                                    "cpu_went_to": held_by}
        result["elapsed_s"] = round(time.monotonic() - started, 1)
        result["targets"] = targets(result)
        markdown = "\n\n".join([report(result), *closing_sections(result),
                                 f"(whole benchmark: {result['elapsed_s']:.0f} s)"])
        return print_and_save(markdown, result, args.json)
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    raise SystemExit(main())
