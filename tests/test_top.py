"""``rtloop top``: finds a running app through its registry and shows live task counters."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rtloop.cli import top_view
from rtloop.cli.main import main as cli_main
from rtloop.toolbox.monitor import (
    MAX_SUMMARY_BYTES,
    SCHED_NAMES,
    AppView,
    Monitor,
    TaskView,
    find_apps,
    live_summary_line,
    read_proc,
)

NOOP = '''
from rtloop import Runnable


class Noop(Runnable):
    """Does nothing, every period."""

    n_inputs = 0
    n_outputs = 1

    def step(self, u, y):
        y[0] = 0.0
'''


def app_toml(name: str) -> str:
    tasks = "".join(f'\n[tasks.{task}]\nrunnable = "noop_top:Noop"\nperiod_ns = 1_000_000\npriority = {prio}\n'
                    for task, prio in (("fast", 70), ("slow", 60)))
    return f'name = "{name}"\n{tasks}'


def cycles_in_frame(text: str, task: str) -> int:
    """The ``cycle`` cell of ``task``'s row in a rendered frame."""
    lines = text.splitlines()
    header = next(line for line in lines if "│ task" in line)
    column = [cell.strip() for cell in header.split("│")].index("cycle")
    row = next(line for line in lines if line.startswith(f"│ {task} "))
    return int(row.split("│")[column].strip().replace(",", ""))


def frame(app: str, capsys: pytest.CaptureFixture[str]) -> str:
    assert cli_main(["top", app, "--once", "--interval", "0.2"]) == 0
    return capsys.readouterr().out


@pytest.fixture
def running_app(tmp_path: Path):
    name = f"toptest{os.getpid()}"
    (tmp_path / "noop_top.py").write_text(NOOP)
    (tmp_path / "app.toml").write_text(app_toml(name))
    log = tmp_path / "run.log"
    with log.open("w") as output:
        process = subprocess.Popen(
            [sys.executable, "-m", "rtloop.cli", "run", str(tmp_path / "app.toml"), "--duration", "200",
             "--out", str(tmp_path / "out"), "--quiet"],
            stdout=output, stderr=subprocess.STDOUT,
        )
    try:
        deadline = time.monotonic() + 60  # a bound: 11 s went by under load (a Python start-up, then the tasks')
        monitor = Monitor(name)
        while True:
            views = [v for v in monitor.snapshot() if v.pid == process.pid]
            if views and len(views[0].tasks) == 2 and all(t.cycles > 0 for t in views[0].tasks):
                break
            if process.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"app did not start running (exit {process.poll()}): {log.read_text()}")
            time.sleep(0.05)
        yield name, process
    finally:
        process.terminate()
        process.wait(timeout=60)


@pytest.mark.slow
def test_top_once_shows_every_task_counting(running_app, capsys: pytest.CaptureFixture[str]) -> None:
    name, process = running_app
    first = frame(name, capsys)
    time.sleep(0.3)
    second = frame(name, capsys)
    assert f"{name}  (supervisor pid {process.pid})" in first
    for task in ("fast", "slow"):
        before, after = cycles_in_frame(first, task), cycles_in_frame(second, task)
        assert 0 < before < after, (task, before, after)
    assert "lat max" in second and "n/a" in second  # the note on the running maximum; GC not readable

    monitor = Monitor(name)
    (view,) = monitor.snapshot()
    # the rate is cycles over the monitor's own clock between two snapshots: over 1 s, a loaded machine
    # running this process 0.1 s late at one of them stays within the 30 % asked below (over 0.3 s, 33 %)
    monitor.poll_for(1.0)
    (later,) = monitor.snapshot()
    for task, again in zip(view.tasks, later.tasks, strict=True):
        assert again.cycles > task.cycles
        assert again.cycles_per_s == pytest.approx(1000, rel=0.3)  # 1 kHz
        assert again.pid > 0 and again.pid != process.pid
        assert again.latency_max_ns >= again.latency_now_ns
        assert again.cpu_percent is not None and again.minflt is not None
        assert again.nonvoluntary_ctxt_switches is not None
        assert again.sched.split(":")[0] in ("fifo", "other")


@pytest.mark.slow
def test_top_forgets_an_app_that_ended(running_app, capsys: pytest.CaptureFixture[str]) -> None:
    name, process = running_app
    process.terminate()
    process.wait(timeout=60)
    assert cli_main(["top", name, "--once", "--interval", "0.1"]) == 2
    assert f"no running app named '{name}'" in capsys.readouterr().err


@pytest.mark.parametrize("once", [["--once"], []], ids=["once", "live"])
def test_top_of_an_app_that_does_not_run_names_it_exit_2(once: list[str], rtloop_env: dict[str, str]) -> None:
    # The live view too: it once waited, empty, for ever, for an app whose name was mistyped.
    name = f"top_nope_{os.getpid()}"
    command = [sys.executable, "-m", "rtloop.cli", "top", name, *once, "--interval", "0.1"]
    try:
        result = subprocess.run(command, env=rtloop_env, stdin=subprocess.DEVNULL, capture_output=True, text=True,
                                timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail(f"rtloop top {name} {' '.join(once)} went on for 60 s instead of refusing the name")
    err = result.stderr.strip()
    assert result.returncode == 2, err
    assert err.startswith(f"rtloop top: no running app named '{name}'; running: ") and len(err.splitlines()) == 1, err
    assert result.stdout == ""


def test_registry_of_a_dead_supervisor_is_ignored(tmp_path: Path) -> None:
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    for app, pid in (("gone", dead.pid), ("here", os.getpid())):
        registry = {"app": app, "pid": pid, "ports": {}, "tasks": {"t": f"rtloop-{app}-{pid}-00000000-t.task"}}
        (tmp_path / f"rtloop-{app}-{pid}-00000000-registry.json").write_text(json.dumps(registry))
    (tmp_path / "rtloop-broken-1-00000000-registry.json").write_text("{")
    assert [r.app for r in find_apps(shm_dir=tmp_path)] == ["here"]
    assert find_apps("gone", shm_dir=tmp_path) == []
    # its status segment does not exist: the app is listed with no task rows, not an error
    (view,) = Monitor(shm_dir=tmp_path).snapshot()
    assert view.app == "here" and view.tasks == []


def test_read_proc_of_this_process() -> None:
    stat = read_proc(os.getpid())
    assert stat is not None
    assert stat.policy in SCHED_NAMES.values()
    assert stat.cpu_ticks >= 0 and stat.minflt > 0
    assert stat.last_cpu in os.sched_getaffinity(0) or stat.last_cpu >= 0
    assert read_proc(2**22 + 12345) is None


def test_narrow_terminal_keeps_the_timing_columns() -> None:
    from rich.console import Console

    row = TaskView(name="controller", state="RUNNING", pid=4242, cpu="1 (on 1)", sched="fifo:80", cycles=123_456,
                       cycles_per_s=1000.0, overruns=0, deadline_misses=2, stale_reads=0, latency_now_ns=21_000,
                       latency_max_ns=180_000, exec_last_ns=95_000, cpu_percent=11.5, nonvoluntary_ctxt_switches=3,
                       minflt=25_000, majflt=0)
    views = [AppView("jiwy", 1, [row])]
    for width, expect_gc in ((80, False), (250, True)):
        console = Console(width=width, record=True)
        console.print(top_view.render(views, width))
        text = console.export_text()
        assert max(len(line) for line in text.splitlines()) <= width
        assert "123,456" in text and "180.0" in text and "lat max µs" in text
        assert ("│ GC" in text or " GC │" in text) is expect_gc


def _summary_text(padding: int = 0) -> str:
    return json.dumps({"tasks": {"ctl": {"latency_ns": {"p99": 12_000, "max": 30_000}}},
                       "recording": {"stopped": None, "keep_s": None}, "pad": "x" * padding})


def test_the_live_summary_line_reads_a_regular_summary_json(tmp_path: Path) -> None:
    path = tmp_path / "summary.json"
    path.write_text(_summary_text())
    line = live_summary_line(str(path))
    assert line.startswith("summary.json (") and "ctl p99 12.0 max 30.0 µs; recording: everything kept" in line


def test_a_registry_naming_a_fifo_or_a_huge_file_as_its_summary_gives_no_line(tmp_path: Path) -> None:
    # The summary path comes from a registry another user wrote, when root runs rtloop top.
    import threading

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    huge = tmp_path / "huge.json"
    huge.write_text(_summary_text(padding=MAX_SUMMARY_BYTES))
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(live_summary_line(str(p)) for p in (fifo, huge)),
                              daemon=True)
    reader.start()
    reader.join(timeout=30)
    assert not reader.is_alive(), "rtloop top waited on a FIFO named as a summary.json"
    assert lines == ["", ""]


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root: to give a file to another uid")
def test_a_registry_naming_another_users_file_or_a_link_as_its_summary_gives_no_line(tmp_path: Path) -> None:
    theirs = tmp_path / "theirs.json"  # root's, or a third user's: not the app's
    theirs.write_text(_summary_text())
    os.chown(theirs, 65534, 65534)
    assert live_summary_line(str(theirs), app_uid=1234) == ""
    assert live_summary_line(str(theirs), app_uid=65534).startswith("summary.json (")
    assert live_summary_line(str(theirs), app_uid=0).startswith("summary.json (")  # root's run, given to the sudo user
    link = tmp_path / "link.json"
    link.symlink_to(theirs)
    assert live_summary_line(str(link), app_uid=65534) == ""
