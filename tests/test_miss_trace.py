"""``rtloop run --trace-misses``: the kernel's scheduler and IRQ events name who held a late cycle's CPU.

Parsing and attribution are tested on trace lines in the kernel's text format; on a kernel without
tracefs (this machine's) the option is one line in the notes and the run goes on; in the PREEMPT_RT
guest (tracefs, osnoise and timerlat built in) a thread the test starts holds the task's CPU and
must be named by the trace.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import rtloop
from conftest import scaled_ns, scaled_s, unique_name
from rt_test_runnables import Noop
from rtloop import App
from rtloop.linux import trace
from rtloop.stats.miss_causes import IRQ, THREAD, UNEXPLAINED, Evidence, Miss, explain

SWITCH = ("{comm}-{pid} [001] d..2. {ts}: sched_switch: prev_comm={comm} prev_pid={pid} prev_prio=120 "
          "prev_state=S ==> next_comm={next} next_pid={next_pid} next_prio={prio}")


def _switch(ts: str, comm: str, pid: int, next_comm: str, next_pid: int, prio: int) -> str:
    return "  " + SWITCH.format(comm=comm, pid=pid, ts=ts, next=next_comm, next_pid=next_pid, prio=prio)


def test_trace_lines_are_parsed_into_switches_and_handlers() -> None:
    switch = trace.parse(_switch("100.000100", "<idle>", 0, "rtloop hog", 77, 9))
    assert switch == trace.Event(100_000_100_000, "switch", "rtloop hog (pid 77, FIFO/RR 90)", 90,
                                 prev="<idle> (pid 0, other)", prev_priority=0, context_pid=0)
    irq = trace.parse("  <idle>-0 [001] d.h1. 100.000200: irq_handler_entry: irq=24 name=virtio0-input.0")
    assert irq == trace.Event(100_000_200_000, "irq", "IRQ 24 (virtio0-input.0)", context_pid=0)
    assert trace.parse("  <idle>-0 [001] d.h1. 100.000300: irq_handler_exit: irq=24 ret=handled") == trace.Event(
        100_000_300_000, "irq_end", "IRQ 24", context_pid=0)
    wakeup = trace.parse("  <idle>-0 [001] dNh2. 100.000400: sched_wakeup: comm=rtloop hog pid=77 prio=9 "
                         "target_cpu=001")
    assert wakeup == trace.Event(100_000_400_000, "wakeup", "rtloop hog (pid 77, FIFO/RR 90)", 90, context_pid=0)
    assert trace.parse("  <idle>-0 [001] dNh2. 100.000400: sched_wakeup: comm=x pid=8 prio=120 "
                       "target_cpu=000") is None  # woken onto another CPU
    assert trace.parse("# tracer: nop") is None


def test_held_sums_who_had_the_cpu_in_a_window() -> None:
    tracer = trace.MissTracer(Path("/nonexistent"), {1})
    lines = [_switch("100.000000", "<idle>", 0, "task", 10, 19),      # the task runs
             _switch("100.000050", "task", 10, "swapper/1", 0, 120),  # and sleeps
             _switch("100.001000", "swapper/1", 0, "rtloop-hog", 77, 9),  # the release: the hog has the CPU
             "  rtloop-hog-77 [001] d.h1. 100.002000: irq_handler_entry: irq=24 name=eth0",
             "  rtloop-hog-77 [001] d.h1. 100.002100: irq_handler_exit: irq=24 ret=handled",
             _switch("100.004000", "rtloop-hog", 77, "task", 10, 19)]   # 3 ms later, the task
    for line in lines:
        event = trace.parse(line)
        assert event is not None
        tracer.events[1].append(event)
    held = tracer.held(1, 100_001_000_000, 100_004_050_000, frozenset({10}))
    assert held[0] == {"who": "rtloop-hog (pid 77, FIFO/RR 90)", "kind": "thread", "ran_ns": 3_000_000,
                       "priority": 90}
    assert {"who": "IRQ 24 (eth0)", "kind": "irq", "ran_ns": 100_000, "priority": -1} in held
    assert all("task" not in item["who"] for item in held)  # the late task itself is not its own cause
    miss = Miss("plant", 1, 100_001_000_000, 100_004_000_000, 100_004_050_000, 1_000_000)
    cause = explain(miss, Evidence(cpu=1, priority=80, traced=held))
    assert cause.cls == THREAD
    assert cause.text.startswith("preempted by a higher-priority thread: rtloop-hog (pid 77, FIFO/RR 90) had CPU 1 "
                                 "for 3.0 ms")
    assert explain(miss, Evidence(cpu=1, priority=90, traced=held)).text.startswith("held by another thread: ")
    # a SCHED_OTHER thread on the CPU cannot hold a FIFO task off: the task was not runnable yet
    lower = [{"who": "nm (pid 9, other)", "kind": "thread", "ran_ns": 2_900_000, "priority": 0}]
    cause = explain(miss, Evidence(cpu=1, priority=80, traced=lower))
    assert cause.cls == UNEXPLAINED and "cannot hold this task off" in cause.text
    irq_only = [{"who": "IRQ 24 (eth0)", "kind": "irq", "ran_ns": 2_900_000}]
    assert explain(miss, Evidence(cpu=1, traced=irq_only)).cls == IRQ


def test_without_tracefs_trace_misses_is_one_note_and_the_run_goes_on(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(trace, "find_tracefs", lambda: None)  # a kernel built without it
    monkeypatch.setattr(trace, "kernel_has_tracefs", lambda: False)
    app = App(unique_name("trace_none"))
    app.add_task("idle", Noop(), period_ns=10_000_000, policy="other", cpu=0)
    summary = rtloop.run(app, 0.3, tmp_path / "run", trace_misses=True)
    notes = [note for note in summary.notes if note.startswith("--trace-misses:")]
    assert len(notes) == 1 and "no tracefs" in notes[0] and "\n" not in notes[0]
    assert summary.tasks["idle"].timing.cycles > 0


@pytest.mark.alone
def test_a_private_tracefs_mount_is_gone_after_the_run(tmp_path: Path) -> None:
    usable, why = trace.availability()
    if not usable or trace.find_tracefs() is not None:
        pytest.skip(why or "tracefs is mounted here already: rtloop mounts nothing")
    before = Path("/proc/self/mounts").read_text().count("tracefs")
    app = App(unique_name("trace_mount"))
    app.add_task("idle", Noop(), period_ns=10_000_000, policy="other", cpu=0)
    summary = rtloop.run(app, 0.3, tmp_path / "run", trace_misses=True)
    assert not [note for note in summary.notes if note.startswith("--trace-misses:")], summary.notes
    assert Path("/proc/self/mounts").read_text().count("tracefs") == before


HOLDER = """
import ctypes, os, sys, time
ctypes.CDLL(None).prctl(15, b"rtloop-holder", 0, 0, 0)  # PR_SET_NAME: the name the trace shows
os.sched_setaffinity(0, {int(sys.argv[1])})
os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(90))
print("holding", flush=True)
while True:
    busy_until = time.monotonic_ns() + int(sys.argv[2])
    while time.monotonic_ns() < busy_until:
        pass
    time.sleep(int(sys.argv[3]) / 1e9)
"""


@pytest.mark.rt
@pytest.mark.timeout(1200)
def test_held_sees_a_thread_whose_switch_out_of_idle_went_untraced() -> None:
    """Lines as a 6.18 VM kernel records them: never a ``swapper → thread`` switch, only the wake-up
    (from the idle context) and the thread's own switch out. The hog ran from its wake-up."""
    tracer = trace.MissTracer(Path("/nonexistent"), {1})
    lines = [_switch("100.000000", "task", 10, "swapper/1", 0, 120),
             "  <idle>-0 [001] dNh2. 100.000900: sched_wakeup: comm=rtloop-hog pid=77 prio=9 target_cpu=001",
             # (idle → rtloop-hog, untraced)
             "  <idle>-0 [001] dNh2. 100.001000: sched_wakeup: comm=task pid=10 prio=49 target_cpu=001",
             "  rtloop-hog-77 [001] ..s1. 100.002000: softirq_entry: vec=1 [action=TIMER]",
             "  rtloop-hog-77 [001] ..s1. 100.002010: softirq_exit: vec=1 [action=TIMER]",
             "  rtloop-hog-77 [001] d..2. 100.004000: sched_switch: prev_comm=rtloop-hog prev_pid=77 prev_prio=9 "
             "prev_state=S ==> next_comm=task next_pid=10 next_prio=49"]
    for line in lines:
        event = trace.parse(line)
        assert event is not None
        tracer.events[1].append(event)
    held = tracer.held(1, 100_001_000_000, 100_004_050_000, frozenset({10}))
    assert held[0] == {"who": "rtloop-hog (pid 77, FIFO/RR 90)", "kind": "thread", "ran_ns": 3_000_000,
                       "priority": 90}
    # from before the window: only the part inside counts; idle (swapper) is never a holder
    wide = tracer.held(1, 100_000_000_000, 100_004_000_000, frozenset({10}))
    assert wide[0]["ran_ns"] == 3_100_000 and not [item for item in wide if "swapper" in str(item["who"])]
    # a switch out of a thread never seen before on the CPU (no wake-up, no event in its context): not credited
    tracer.events[1].clear()
    for line in (lines[0], lines[-1]):
        event = trace.parse(line)
        assert event is not None
        tracer.events[1].append(event)
    assert [item for item in tracer.held(1, 100_001_000_000, 100_004_050_000, frozenset({10}))
            if "rtloop-hog" in str(item["who"])] == []


@pytest.mark.alone
def test_trace_misses_names_the_thread_that_held_the_tasks_cpu(tmp_path: Path) -> None:
    """A process of this test, at FIFO 90 on the task's CPU, spins for 8 periods now and then: the
    task (FIFO 50) wakes late, and the trace names the thread (its comm, set here) as the holder.
    Runs here (tracefs mounted privately) and in the PREEMPT_RT guest (-m rt)."""
    usable, why = trace.availability()
    if not usable:
        pytest.skip(why)
    cpu = max(os.sched_getaffinity(0))
    period_ns = scaled_ns(1_000_000)
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(cpu), str(8 * period_ns), str(40 * period_ns)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "holding"
        app = App(unique_name("trace_guest"))
        app.add_task("held", Noop(), period_ns=period_ns, priority=50, cpu=cpu)
        rtloop.run(app, scaled_s(3.0), tmp_path / "run", trace_misses=True)
    finally:
        holder.kill()
        holder.wait()
        if holder.stdout is not None:
            holder.stdout.close()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert not [note for note in summary["notes"] if note.startswith("--trace-misses:")], summary["notes"]
    misses = summary["misses"]
    assert misses["total"] > 0
    traced = [m for m in misses["first"] if "(traced)" in m["cause"]]
    assert traced, misses["first"]
    assert any(m["cause"].startswith("preempted by a higher-priority thread: rtloop-holder (pid ") for m in traced)


def test_timer_and_syscall_lines_are_parsed_for_the_wake_up_bench() -> None:
    armed = trace.parse("  python3-4242 [001] d..1. 23456.123456789: hrtimer_start: hrtimer=00000000a1b2c3d4 "
                        "function=hrtimer_wakeup expires=23456124000000 softexpires=23456124000000 "
                        "mode=ABS was_armed=0")
    assert armed == trace.Event(23_456_123_456_789, "sleep_armed", "00000000a1b2c3d4", context_pid=4242,
                                expires_ns=23_456_124_000_000)  # the stamp to the ns: no float on the way
    assert trace.parse("  python3-4242 [001] d..1. 1.0: hrtimer_start: hrtimer=0000000011 function=tick_nohz_handler "
                       "expires=2 softexpires=2 mode=ABS") is None  # not a sleeping thread's timer
    fired = trace.parse("  <idle>-0 [001] d.h1. 23456.124003000: hrtimer_expire_entry: hrtimer=00000000a1b2c3d4 "
                        "function=hrtimer_wakeup now=23456124002900")
    assert fired == trace.Event(23_456_124_003_000, "sleep_fired", "00000000a1b2c3d4", context_pid=0)
    returned = trace.parse("  python3-4242 [001] ..... 23456.124010000: sys_exit: NR 230 = 0")
    assert returned == trace.Event(23_456_124_010_000, "syscall_exit", "230", context_pid=4242)


def test_an_untraced_switch_in_is_put_back_once_at_the_first_sign_of_the_thread() -> None:
    lines = [_switch("100.000000", "task", 10, "swapper/1", 0, 120),  # traced: a thread's switch into idle
             "  <idle>-0 [001] d.h1. 100.000500: irq_handler_entry: irq=24 name=eth0",  # idle's: no switch
             "  task-10 [001] ..... 100.001000: sys_exit: NR 230 = 0",  # (idle → task, untraced)
             "  task-10 [001] d.h1. 100.001100: irq_handler_entry: irq=24 name=eth0",  # task still runs
             _switch("100.002000", "task", 10, "swapper/1", 0, 120),
             "  <idle>-0 [001] dNh2. 100.002500: sched_wakeup: comm=hog pid=77 prio=9 target_cpu=001",
             "  hog-77 [001] ..s1. 100.003000: softirq_entry: vec=1 [action=TIMER]"]  # (idle → hog at its wake-up)
    events = [event for line in lines if (event := trace.parse(line)) is not None]
    switches = [(event.at_ns, event.prev, event.who, event.inferred)
                for event in trace.with_untraced_switches(events) if event.kind == "switch"]
    assert switches == [
        (100_000_000_000, "", "task (pid 10)", True),  # its own switch out says it ran: from then, for no time
        (100_000_000_000, "task (pid 10, other)", "swapper/1 (pid 0, other)", False),
        (100_001_000_000, "swapper/1 (pid 0, other)", "task (pid 10, other)", True),
        (100_002_000_000, "task (pid 10, other)", "swapper/1 (pid 0, other)", False),
        (100_002_500_000, "swapper/1 (pid 0, other)", "hog (pid 77, FIFO/RR 90)", True),
    ]


def test_block_request_lines_are_parsed_for_the_disk_bench() -> None:
    issued = trace.parse("  python3-4242 [000] ..... 100.000001: block_rq_issue: 254,0 WS 4096 () 123456 + 8 "
                         "none,0,0 [python3]")
    assert issued == trace.Event(100_000_001_000, "disk_issue", "254,0 123456", context_pid=4242, flags="WS")
    assert issued is not None and issued.context_comm == "python3"
    done = trace.parse("  <idle>-0 [001] d.h1. 100.000201: block_rq_complete: 254,0 WS () 123456 + 8 none,0,0 [0]")
    assert done == trace.Event(100_000_201_000, "disk_done", "254,0 123456", context_pid=0, flags="WS")
    flush = trace.parse("  kworker/0:1H-77 [000] ..... 100.0003: block_rq_issue: 254,0 FF 0 () 0 + 0 none,0,0 "
                        "[kworker/0:1H]")
    assert flush is not None and flush.flags == "FF" and flush.context_comm == "kworker/0:1H"
