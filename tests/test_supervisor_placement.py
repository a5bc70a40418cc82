"""The supervisor keeps off the CPUs its tasks are pinned to while they run (linux/hygiene.py).

On a kernel that is not fully preemptible a task woken on a CPU where the supervisor is inside a
system call waits for that call to return, whatever the priorities: the supervisor must not be
there. These tests look at where the kernel allows the supervisor's threads to run, not at timings.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest

import rtloop
from conftest import unique_name
from rt_test_runnables import Counter
from rtloop import App
from rtloop.linux.hygiene import away_from_task_cpus

CPUS = sorted(os.sched_getaffinity(0))


def threads_cpus() -> dict[int, set[int]]:
    """Where each thread of this process may run now."""
    return {int(tid): os.sched_getaffinity(int(tid)) for tid in os.listdir("/proc/self/task")}


@pytest.mark.skipif(len(CPUS) < 2, reason="needs a CPU for the task and another for the supervisor")
def test_while_the_tasks_run_no_thread_of_the_supervisor_may_run_on_a_tasks_cpu(tmp_path: Path) -> None:
    task_cpu = CPUS[-1]
    app = App(unique_name("placement"))
    app.add_task("count", Counter(), period_ns=1_000_000, policy="other", cpu=task_cpu)
    seen: list[dict[int, set[int]]] = []
    waiting = threading.Event()  # a thread of the caller's, started before the run, moves too
    helper = threading.Thread(target=waiting.wait, daemon=True)
    helper.start()
    before = threads_cpus()
    try:
        rtloop.run(app, 0.3, tmp_path / "run", on_progress=lambda _progress: seen.append(threads_cpus()))
        after = threads_cpus()
    finally:
        waiting.set()
        helper.join()
    assert seen, "the run called on_progress at no drain"
    for threads in seen:
        assert helper.native_id in threads
        for tid, cpus in threads.items():
            assert task_cpu not in cpus, f"thread {tid} of the supervisor may run on the task's CPU {task_cpu}"
    assert after[helper.native_id] == before[helper.native_id]  # each thread gets its CPUs back
    assert os.sched_getaffinity(0) == set(CPUS)


def test_with_every_cpu_taken_by_a_task_the_supervisor_keeps_its_cpus() -> None:
    with away_from_task_cpus(CPUS) as allowed:
        assert allowed == frozenset(CPUS)
        assert os.sched_getaffinity(0) == set(CPUS)
    with away_from_task_cpus([]) as allowed:
        assert allowed == frozenset(CPUS)
