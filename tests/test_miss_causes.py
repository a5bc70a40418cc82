"""Why a cycle was late (issue 33): the cause of each miss, decided after the fact.

The decision (``stats/miss_causes.py``) is tested on made-up evidence; the runs below assert the
attribution of the misses that happen, never that misses happen at some rate (this machine is
shared and noisy): a step longer than its period, and a FIFO hog on JIWY's core, guarantee some.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import rtloop
from conftest import cli_env, unique_name
from loaded_runs import JIWY_ON_ONE_CPU, stress_ng
from rt_test_runnables import Noop, SpinFor
from rtloop import App
from rtloop.cli.main import main
from rtloop.linux import trace
from rtloop.record.summary import SUMMARY_BOUND_BYTES
from rtloop.runtime.evidence import MissWatch, TaskFacts
from rtloop.stats.miss_causes import (
    MACHINE,
    RUN_QUEUE,
    STEP,
    TASK,
    THREAD,
    UNEXPLAINED,
    Evidence,
    Miss,
    MissLedger,
    explain,
)

MS = 1_000_000
T0 = 10_000 * MS


def _miss(latency_ns: int, exec_ns: int, period_ns: int = MS, cycle: int = 7, task: str = "plant") -> Miss:
    release = T0 + cycle * period_ns
    return Miss(task, cycle, release, release + latency_ns, release + latency_ns + exec_ns, period_ns)


def _counters(on_cpu_ns: int, run_delay_ns: int = 0, bracketed: int = 1) -> dict[str, int]:
    return {"since_cycle": 6, "bracketed": bracketed, "on_cpu_ns": on_cpu_ns, "run_delay_ns": run_delay_ns,
            "involuntary_switches": 0, "minor_faults": 0, "major_faults": 0}


def test_a_step_longer_than_its_period_is_an_overrun_of_the_step_with_its_time() -> None:
    cause = explain(_miss(30_000, 2_300_000), Evidence(cpu=1, counters=_counters(2_250_000)))
    assert cause.cls == STEP
    assert cause.text.startswith("step overran: 2.3 ms of a 1.0 ms period")


def test_a_late_wake_up_is_not_blamed_on_a_short_step() -> None:
    """The issue's case: woke 4.3 ms late, step 78 µs, while the hypervisor stalled the CPU."""
    miss = _miss(4_300_000, 78_000, period_ns=2 * MS)
    cause = explain(miss, Evidence(cpu=1, window_ns=50 * MS, steal_ns=10 * MS))
    assert cause.cls == MACHINE and "steal +10.0 ms on CPU 1" in cause.text
    assert "woke 4.3 ms late, step took 78 µs" in cause.text
    # without any evidence it is unexplained, never the step's
    assert explain(miss, Evidence(cpu=1)).cls == UNEXPLAINED


def test_a_long_wall_time_with_little_cpu_time_is_not_the_steps() -> None:
    """Wall time over the period, but the thread was on the CPU 300 µs: someone else took the rest."""
    miss = _miss(20_000, 2_500_000)
    cause = explain(miss, Evidence(cpu=0, counters=_counters(300_000, run_delay_ns=2_100_000)))
    assert cause.cls == RUN_QUEUE and "waited 2.1 ms on the run queue" in cause.text
    # nobody to name, but its own CPU time says it was not the step: unexplained, never "step overran"
    cause = explain(miss, Evidence(cpu=0, counters=_counters(300_000)))
    assert cause.cls == UNEXPLAINED and "300 µs of it on the CPU" in cause.text


def test_a_higher_priority_thread_that_ran_meanwhile_is_named_before_a_stall() -> None:
    hog = {"label": "rtloop-hog (pid 5, tid 5, FIFO 90)", "priority": 90, "relation": "higher", "ran_ns": 3 * MS}
    evidence = Evidence(cpu=1, window_ns=50 * MS, steal_ns=10 * MS, threads=[hog])
    cause = explain(_miss(2_900_000, 20_000), evidence)
    assert cause.cls == THREAD
    assert cause.text.startswith("preempted by a higher-priority thread: rtloop-hog (pid 5")
    # a thread that ran far less than the cycle lost does not explain it
    small = dict(hog, ran_ns=100_000)
    assert explain(_miss(2_900_000, 20_000), Evidence(cpu=1, threads=[small])).cls == UNEXPLAINED


def test_another_tasks_step_on_the_same_cpu_is_named() -> None:
    other = {"task": "controller", "cycle": 41, "overlap_ns": 1_800_000, "exec_ns": 1_900_000, "priority": 81,
             "relation": "higher"}
    cause = explain(_miss(1_900_000, 15_000), Evidence(cpu=1, tasks=[other]))
    assert cause.cls == TASK and "controller's step (cycle 41, 1.9 ms, priority 81)" in cause.text


def _woken_late_at_40(base: int) -> np.ndarray:
    """A 1 ms task's timing records around ``base`` (cycle 40's release): cycle 39 on time, cycle 40
    woken 2.52 ms late (held while another task stepped), then cycles 41-42 skipped, 43 on time."""
    return np.array([[39, base - MS, base - MS + 8_000, base - MS + 30_000],
                     [40, base, base + 2_520_000, base + 2_540_000],
                     [43, base + 3 * MS, base + 3 * MS + 9_000, base + 3 * MS + 30_000]], dtype=np.int64)

def test_the_watch_finds_a_higher_priority_task_on_the_same_cpu_from_the_records() -> None:
    facts = {"plant": TaskFacts(MS, 1, 80, True), "controller": TaskFacts(MS, 1, 81, True),
             "far": TaskFacts(MS, 0, 90, True)}
    watch = MissWatch(facts=facts)
    base = T0 + 40 * MS
    # the controller's cycle 40 runs 2.5 ms from its release; plant's cycle 40 waits for it
    watch.add_timing("controller", np.array([[40, base, base + 10_000, base + 2_510_000]], dtype=np.int64))
    watch.add_timing("far", np.array([[40, base, base + 5_000, base + 20_000]], dtype=np.int64))
    watch.add_timing("plant", _woken_late_at_40(base))
    watch.finish()
    ledger = watch.ledger.to_json()
    assert ledger["total"] == 2  # the controller's own long step is a miss too: the step's
    assert ledger["counts"] == {"plant": {"late wake-up": {TASK: 1}}, "controller": {"overrun": {STEP: 1}}}
    first = next(m for m in ledger["first"] if m["task"] == "plant")
    assert first["cycle"] == 40 and first["skipped"] == 2 and "controller's step (cycle 40" in first["cause"]
    assert [t["task"] for t in first["evidence"]["tasks"]] == ["controller"]  # "far" is on another CPU


def test_the_ledger_keeps_the_first_in_full_and_counts_the_rest() -> None:
    ledger = MissLedger(first_in_full=3)
    for cycle in range(10):
        miss = _miss(10_000, 2 * MS, cycle=cycle)
        ledger.add(miss, Evidence(cpu=1), explain(miss, Evidence(cpu=1, counters=_counters(2 * MS))))
    out = ledger.to_json()
    assert out["total"] == 10 and len(out["first"]) == 3 and out["counts"]["plant"]["overrun"][STEP] == 10
    assert out["lines"] == ["plant: 10 overruns, all the step overran; worst: step overran: 2.0 ms of a 1.0 ms "
                            "period (2.0 ms on the CPU)"]


def test_the_models_catch_up_line_names_the_task_and_the_true_cause() -> None:
    ledger = MissLedger()
    miss = _miss(4_300_000, 78_000, period_ns=2 * MS, task="CartPole")
    evidence = Evidence(cpu=1, window_ns=50 * MS, steal_ns=10 * MS)
    ledger.add(miss, evidence, explain(miss, evidence))
    ledger.catch_up["CartPole"] = 2
    line = ledger.lines()[-1]
    assert line.startswith("CartPole: the model took 2 extra steps")
    assert "while the machine stalled" in line and "(not by its step)" in line
    assert "its step overran" not in line


def _run(app: App, out: Path, duration_s: float) -> dict:
    rtloop.run(app, duration_s, out)
    return json.loads((out / "summary.json").read_text())


@pytest.mark.alone
def test_a_2ms_step_in_a_1ms_task_is_a_step_overran_with_its_time(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    app = App(unique_name("misses_overrun"))
    app.add_task("slow", SpinFor(2 * MS), period_ns=MS, priority=60, cpu=1)
    summary = _run(app, tmp_path / "run", 0.5)
    misses = summary["misses"]
    assert misses["total"] == summary["tasks"]["slow"]["deadline_misses"] > 0  # every cycle overruns
    blamed = [m for m in misses["first"] if m["cause_class"] == STEP]
    assert blamed, misses["first"]
    for miss in blamed:  # the step is blamed only when its time reached the period, and says it
        assert miss["exec_ns"] >= MS
        assert re.match(r"step overran: \d+\.\d ms of a 1\.0 ms period", miss["cause"])
    assert any(line.startswith("slow: ") and "the step overran" in line for line in misses["lines"])
    from rtloop.report.build import build_report

    report = build_report([tmp_path / "run"], tmp_path / "report", write_html=True)
    assert report.html is not None
    html = report.html.read_text()
    assert "Why cycles were late" in html and "the step overran" in html
    capsys.readouterr()
    assert main(["why", str(tmp_path / "run"), "--cycle", str(blamed[0]["cycle"]), "--task", "slow"]) == 0
    said = capsys.readouterr().out
    assert f"slow cycle {blamed[0]['cycle']}: overrun" in said and "cause: step overran" in said
    assert "its thread's counters" in said


@pytest.mark.alone
def test_the_console_summary_has_a_line_per_cause_and_why_answers_on_the_command_line(tmp_path: Path) -> None:
    app_file = tmp_path / "slow.toml"
    name = unique_name("misses_console")
    app_file.write_text(f'name = "{name}"\n[tasks.slow]\nrunnable = "rt_test_runnables:SpinFor"\n'
                        f"args = {{ spin_ns = {2 * MS} }}\nperiod_ns = {MS}\npriority = 60\ncpu = 1\n")
    env = {**cli_env(), "PYTHONPATH": str(Path(__file__).parent)}
    done = subprocess.run([sys.executable, "-m", "rtloop", "run", str(app_file), "--duration", "0.5", "--out",
                           str(tmp_path / "run")], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    assert re.search(r"^misses: slow: \d+ overruns? .*the step overran", done.stdout, re.M), done.stdout
    assert "skipped releases (its step overran)" not in done.stdout + done.stderr
    why = subprocess.run([sys.executable, "-m", "rtloop", "why", str(tmp_path / "run")], capture_output=True,
                         text=True, env=env, timeout=60)
    assert why.returncode == 0 and "deadline misses" in why.stdout and "slow cycle" in why.stdout
    bad = subprocess.run([sys.executable, "-m", "rtloop", "why", str(tmp_path / "nothing")], capture_output=True,
                         text=True, env=env, timeout=60)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "not a run directory" in bad.stderr


def test_an_on_time_task_has_no_misses_to_explain(tmp_path: Path) -> None:
    app = App(unique_name("misses_none"))
    app.add_task("idle", Noop(), period_ns=20 * MS, policy="other")
    summary = _run(app, tmp_path / "run", 0.3)
    assert summary["misses"]["total"] == summary["tasks"]["idle"]["deadline_misses"]


HOG = """
import ctypes, os, sys, time
ctypes.CDLL(None).prctl(15, b"rtloop-hog", 0, 0, 0)  # PR_SET_NAME: what /proc calls the thread
os.sched_setaffinity(0, {int(sys.argv[1])})
os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(90))
print("holding", flush=True)
end = time.monotonic() + float(sys.argv[2])
while time.monotonic() < end:  # 3 ms of the CPU every 40 ms, above the tasks
    busy_until = time.monotonic_ns() + 3_000_000
    while time.monotonic_ns() < busy_until:
        pass
    time.sleep(0.037)
"""


@pytest.mark.alone
@pytest.mark.rt
@pytest.mark.timeout(300)
@pytest.mark.parametrize("traced", [False, True], ids=["evidence", "trace-misses"])
def test_jiwy_with_a_fifo_hog_on_its_core_blames_the_hog(tmp_path: Path, traced: bool) -> None:
    """A FIFO-90 thread holds JIWY's core 3 ms every 40 ms: the tasks (FIFO 80/81, 1 ms) miss. Every
    miss the hog can account for (late by at most its 3 ms burst and a period) names it, as a
    higher-priority thread (directly, or through the other task's step it held up); none is blamed
    on a step (~µs). Longer delays on this shared machine come from elsewhere and are not asserted."""
    from conftest import other_cpu

    if os.geteuid() != 0 and os.sched_get_priority_max(os.SCHED_FIFO) <= 0:
        pytest.skip("needs SCHED_FIFO (root or an rtprio limit)")
    cpu = other_cpu()
    name = unique_name("misses_hog")
    app_file = tmp_path / f"{name}.toml"
    app_file.write_text(JIWY_ON_ONE_CPU.format(name=name, cpu=cpu))
    # The hog holds on for longer than the run can take to start (it is killed when the run ends): a
    # run of 1 s whose start took 30 s on a loaded machine would have run beside no hog, missing nothing.
    hog = subprocess.Popen([sys.executable, "-c", HOG, str(cpu), "240"], stdout=subprocess.PIPE, text=True)
    try:
        assert hog.stdout is not None and hog.stdout.readline().strip() == "holding"
        done = subprocess.run([sys.executable, "-m", "rtloop", "run", str(app_file), "--duration", "1", "--out",
                               str(tmp_path / "run"), *(["--trace-misses"] if traced else [])],
                              capture_output=True, text=True, env=cli_env(), timeout=240)
    finally:
        hog.kill()
        hog.wait()
        if hog.stdout is not None:
            hog.stdout.close()
    assert done.returncode == 0, done.stderr
    text = (tmp_path / "run" / "summary.json").read_text()
    assert len(text.encode()) < SUMMARY_BOUND_BYTES  # the misses kept in full: within the bound, half the reserve
    misses = json.loads(text)["misses"]
    assert misses["total"] > 0  # 3 ms above two 1 ms tasks: they cannot all be on time
    named = [m for m in misses["first"] if "rtloop-hog" in m["cause"]]
    assert named, misses["first"]
    assert all(m["cause"].startswith("preempted by a higher-priority thread: rtloop-hog (pid ") for m in named)
    if traced and trace.availability()[0]:  # the kernel's own events said who had the CPU, to the µs
        assert any("(traced)" in m["cause"] for m in named), named
    for miss in misses["first"]:
        assert miss["cause_class"] != STEP, miss
        lost_ns = miss["latency_ns"] if miss["kind"] == "late wake-up" else miss["exec_ns"]
        stalled = miss["cause_class"] == MACHINE and miss["evidence"].get("steal_ns", 0) > 0
        if lost_ns <= 4 * MS and not stalled:  # the hog's reach: a thread held the CPU (the hog, or on this
            # shared machine another engineer's task of the same priority); a hypervisor stall in the same
            # window (steal on the CPU, seen on a quiet machine: +10 ms) is said as the machine's, rightly
            assert miss["cause_class"] == THREAD, miss
    assert re.search(r"^misses: (controller|plant): \d+ late wake-ups? .*\(rtloop-hog \(pid \d+, [^)]*\): \d+",
                     done.stdout, re.M), done.stdout
    # the models' catch-up account: once per task, its name, the true cause (not "its step overran")
    caught_up = re.findall(r"^misses: (\w+): the model took \d+ extra steps.*$", done.stdout, re.M)
    assert caught_up and len(caught_up) == len(set(caught_up)), done.stdout
    lines = [line for line in done.stdout.splitlines() if "extra steps" in line]
    assert all("preempted by a higher-priority thread" in line and "(not by its step)" in line for line in lines)
    assert "its step overran" not in done.stdout + done.stderr
    capsys_free = subprocess.run([sys.executable, "-m", "rtloop", "why", str(tmp_path / "run"), "--cycle",
                                  str(named[0]["cycle"]), "--task", named[0]["task"]], capture_output=True, text=True,
                                 env=cli_env(), timeout=60)
    assert "thread rtloop-hog (pid" in capsys_free.stdout and "cause: preempted" in capsys_free.stdout


@pytest.mark.alone
@pytest.mark.timeout(300)
@pytest.mark.skipif(shutil.which("stress-ng") is None, reason="stress-ng is not installed (apt install stress-ng)")
def test_under_stress_ng_at_sched_other_no_short_step_is_blamed(tmp_path: Path) -> None:
    """A SCHED_OTHER task of 1 ms beside `stress-ng --cpu` (SCHED_OTHER too) on a VM whose hypervisor
    stalls it now and then: its wake-ups are late, its steps short. No miss whose execution time was
    below the period is the step's; each names the run queue, the machine, another thread or says
    it is unexplained."""
    name = unique_name("misses_stress")
    with stress_ng("--cpu", "2", "--timeout", "30s"):
        app = App(name)
        app.add_task("quick", SpinFor(100_000), period_ns=MS, policy="other")
        summary = _run(app, tmp_path / "run", 2.0)
    misses = summary["misses"]
    assert misses["total"] == summary["tasks"]["quick"]["deadline_misses"]
    counted = sum(n for kinds in misses["counts"].values() for by in kinds.values() for n in by.values())
    assert counted == misses["total"]
    for miss in misses["first"]:
        if miss["exec_ns"] < MS:
            assert miss["cause_class"] != STEP, miss
            assert "step overran" not in miss["cause"]
    if misses["total"]:
        assert any(line.startswith("quick: ") for line in misses["lines"])


def test_why_refuses_a_cycle_the_run_does_not_have_and_names_what_it_has(tmp_path: Path) -> None:
    import argparse

    from rtloop.cli import why
    from rtloop.errors import AppError

    run = tmp_path / "run"
    run.mkdir()
    tasks = {name: {"period_ns": MS, "cpu": 1, "priority": 80, "rt": True, "policy": "fifo"} for name in ("a", "b")}
    (run / "summary.json").write_text(json.dumps({"mode": "run", "tasks": tasks, "misses": {"total": 0}}))
    rows = [f"{task},{k},{k * MS},{k * MS + 50_000},{k * MS + 80_000}" for task, last in (("a", 9), ("b", 5))
            for k in range(last + 1)]
    (run / "timing.csv").write_text("task,cycle,release_ns,start_ns,end_ns\n" + "\n".join(rows) + "\n")

    def asked(cycle: int) -> list[str]:
        return why.explain_cycle(run, why._summary(run), cycle, None)

    with pytest.raises(AppError, match=r"cycle 99999 is not in this run's timing.csv \(a: cycles 0 to 9 recorded; "
                                       r"b: cycles 0 to 5 recorded\): give one of its cycles"):
        asked(99999)  # was "not in timing.csv" for each task, exit 0
    assert asked(7) == ["a cycle 7: on time (woke 50 µs after its release, step took 30 µs, period 1.0 ms)",
                        "b cycle 7: not in timing.csv (cycles 0 to 5 recorded)"]
    assert why.run(argparse.Namespace(run_dir=run, cycle=3, task=None)) == 0


def test_why_on_a_planted_or_garbled_run_dir_is_one_line_and_reads_nothing_unbounded(tmp_path: Path) -> None:
    """A FIFO or /dev/zero in place of summary.json or timing.csv waited forever (or read until memory ran
    out), 2 GB of NUL bytes were read as one line, and a summary of another shape was an internal error."""
    import argparse

    from rtloop.cli import why
    from rtloop.errors import AppError

    tasks = {name: {"period_ns": MS, "cpu": 1, "priority": 80, "rt": True, "policy": "fifo"} for name in ("a", "b")}
    good = {"mode": "run", "app": "x", "tasks": tasks, "misses": {"total": 0}}
    rows = "task,cycle,release_ns,start_ns,end_ns\n" + "".join(
        f"{task},{k},{k * MS},{k * MS + 50_000},{k * MS + 80_000}\n" for task in ("a", "b") for k in range(10))

    def run_dir(name: str, summary: object = good, timing: str | None = rows) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        if summary is not None:
            (folder / "summary.json").write_text(json.dumps(summary))
        if timing is not None:
            (folder / "timing.csv").write_text(timing)
        return folder

    def refused(folder: Path, words: str, cycle: int | None = 3) -> None:
        with pytest.raises(AppError, match=words) as caught:
            why.run(argparse.Namespace(run_dir=folder, cycle=cycle, task=None))
        assert "\n" not in str(caught.value)

    fifo = run_dir("fifo_summary", summary=None)
    os.mkfifo(fifo / "summary.json")
    refused(fifo, r"summary.json: not a regular file, so not one rtloop wrote")
    zero = run_dir("zero_timing", timing=None)
    (zero / "timing.csv").symlink_to("/dev/zero")
    refused(zero, r"timing.csv: not a regular file, so not one rtloop wrote$")
    fifo = run_dir("fifo_timing", timing=None)
    os.mkfifo(fifo / "timing.csv")
    refused(fifo, r"timing.csv: not a regular file")
    huge = run_dir("huge_summary")
    with (huge / "summary.json").open("r+b") as file:
        file.truncate(2 << 30)  # sparse: the summary's JSON, then 2 GB of NUL bytes
    refused(huge, r"summary.json: more than 1024 KiB, not a summary rtloop wrote")
    assert why.SUMMARY_READ_MAX_BYTES >= 4 * SUMMARY_BOUND_BYTES  # room above what rtloop writes
    nul = run_dir("nul_timing")
    with (nul / "timing.csv").open("r+b") as file:
        file.truncate(2 << 30)
    refused(nul, r"timing.csv: a line longer than 4096 characters: not a timing.csv rtloop wrote$")
    refused(run_dir("bad_task", {**good, "tasks": {"a": 5}}), r"summary.json: tasks.a: not an rtloop summary's task")
    refused(run_dir("zero_period", {**good, "tasks": {**tasks, "b": {**tasks["b"], "period_ns": 0}}}),
            r"tasks.b: not an rtloop summary's task \(no period_ns > 0\)")
    refused(run_dir("bad_misses", {**good, "misses": "x"}), r"summary.json: misses: not an rtloop summary's", None)
    refused(run_dir("bad_first", {**good, "misses": {"total": 1, "first": [{"task": "a"}]}}),
            r"summary.json: not an rtloop summary rtloop why reads \(KeyError: 'cycle'\)")


def test_a_task_refused_real_time_has_its_misses_explained_as_the_sched_other_task_it_was() -> None:
    # a run without privileges: both tasks declared FIFO 80/81 ran at SCHED_OTHER; the causes said "a thread of the
    # same real-time priority held the CPU" and "held by a higher-priority task: plant's step (priority 81)"
    from types import SimpleNamespace

    from rtloop.runtime.task_messages import TaskReports

    facts = {"controller": TaskFacts(MS, 1, 80, True), "plant": TaskFacts(MS, 1, 81, True)}
    watch = MissWatch(facts=facts)
    reports = TaskReports(watch, [])
    refused = SimpleNamespace(rt=False, policy="other", priority=0)  # what the task process read back
    for name in facts:
        reports._keep(SimpleNamespace(name=name, settings=None), {"kind": "settings", "settings": refused})
    assert not watch.facts["controller"].realtime and watch.facts["controller"].priority == 80
    base = T0 + 40 * MS
    watch.add_timing("plant", np.array([[40, base, base + 10_000, base + 2_510_000]], dtype=np.int64))
    watch.add_timing("controller", _woken_late_at_40(base))
    watch.finish()
    late = next(m for m in watch.ledger.to_json()["first"] if m["task"] == "controller")
    assert late["cause"].startswith("held by another task (this one ran at SCHED_OTHER, not real time): plant's step "
                                    "(cycle 40, 2.5 ms) ran on CPU 1 meanwhile"), late["cause"]
    assert "priority" not in late["cause"]
    thread = {"label": "python (pid 9, tid 9, FIFO 80)", "priority": 80, "relation": "higher", "ran_ns": 3 * MS}
    cause = explain(_miss(2_900_000, 20_000), Evidence(cpu=1, realtime=False, priority=80, threads=[thread]))
    assert cause.text.startswith("preempted by a higher-priority thread: python (pid 9")  # FIFO 80 > SCHED_OTHER
