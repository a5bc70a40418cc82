"""Task processes forked from the supervisor's preloaded task server (runtime/task_start.py) keep
every property a spawned one had: the supervisor's environment and CPUs, only the task's modules,
a single-threaded parent that survives a process-group signal, an end with safe values when the
supervisor is SIGKILLed (and no server left behind), and no stray outliving a killed task."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import rtloop
from conftest import unique_name
from device_test_drivers import read_log
from rtloop import Runnable
from rtloop.app.builder import App
from rtloop.errors import TaskFailed
from rtloop.linux.hygiene import TASK_MARK_ENV
from rtloop.runtime import task_start

TESTS = Path(__file__).resolve().parent
HEAVY = ("rtloop.runtime.supervisor", "rtloop.record.recorder", "rtloop.record.summary", "rtloop.cli.main")
PROBE_ENV = "RTLOOP_TEST_PROBE_VALUE"


class Probe(Runnable):
    """Writes what its process sees in prerun: parent, environment, CPUs, modules."""

    n_inputs = 0
    n_outputs = 1

    def __init__(self, path: str) -> None:
        self.path = path

    def prerun(self) -> None:
        facts = {"pid": os.getpid(), "ppid": os.getppid(), "probe": os.environ.get(PROBE_ENV),
                 "mark": os.environ.get(TASK_MARK_ENV), "cpus": sorted(os.sched_getaffinity(0)),
                 "heavy": [name for name in HEAVY if name in sys.modules]}
        Path(self.path).write_text(json.dumps(facts))

    def step(self, u, y) -> None:
        y[0] = 1.0


class ForksThenDies(Runnable):
    """Forks a child that sleeps (no exec: its /proc environment is its parent's), then SIGKILLs itself."""

    n_inputs = 0
    n_outputs = 1

    def __init__(self, path: str) -> None:
        self.path = path

    def prerun(self) -> None:
        child = os.fork()
        if child == 0:
            time.sleep(120)
            os._exit(0)
        Path(self.path).write_text(str(child))

    def step(self, u, y) -> None:
        os.kill(os.getpid(), signal.SIGKILL)


def _threads(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/task"))


def _ignored_signals(pid: int) -> int:
    with open(f"/proc/{pid}/status") as status:
        line = next(line for line in status if line.startswith("SigIgn:"))
    return int(line.split()[1], 16)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except OSError:
        return False


def _gone_within(pid: int, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if not _alive(pid):
            return True
        time.sleep(0.05)
    return not _alive(pid)


@pytest.fixture
def forking(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(task_start.START_ENV, raising=False)
    if not task_start.forking_allowed():
        pytest.skip("this environment asks BLAS for threads: tasks are spawned here")


def test_a_forked_task_has_the_supervisors_environment_and_cpus_and_only_the_tasks_modules(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, forking: None) -> None:
    server = task_start.start_server()  # started before the variable below exists: the task must not miss it
    assert server is not None
    monkeypatch.setenv(PROBE_ENV, "set after the server started")
    cpus = sorted(os.sched_getaffinity(0))
    app = App(unique_name("fork_env"))
    app.add_task("probe", Probe(str(tmp_path / "facts.json")), period_ns=2_000_000, policy="other")
    rtloop.run(app, 0.1, tmp_path / "out")
    facts = json.loads((tmp_path / "facts.json").read_text())
    assert facts["ppid"] == server == task_start.server_pid(), "the task was not forked from the server"
    assert facts["probe"] == "set after the server started"
    assert facts["mark"] and facts["mark"].startswith(f"{os.getpid()}-") and "task-server" not in facts["mark"]
    assert facts["cpus"] == cpus
    assert facts["heavy"] == []
    # the server: one thread (it forks), SIGTERM and SIGHUP ignored (a process-group signal leaves it to
    # the supervisor to stop the tasks), and it serves the next run too
    assert _threads(server) == 1
    ignored = _ignored_signals(server)
    assert ignored & (1 << (signal.SIGTERM - 1)) and ignored & (1 << (signal.SIGHUP - 1))
    rtloop.run(app, 0.1, tmp_path / "again")
    assert json.loads((tmp_path / "facts.json").read_text())["ppid"] == server


def test_tasks_are_spawned_when_blas_may_use_threads(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "4")
    context, server = task_start.task_context()
    assert context.get_start_method() == "spawn" and server is None
    assert not task_start.child_start(server).forked
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "1")
    monkeypatch.setenv(task_start.START_ENV, "spawn")
    assert task_start.task_context()[0].get_start_method() == "spawn"


def test_what_a_killed_forked_task_forked_ends_with_the_run(tmp_path: Path, forking: None) -> None:
    # Its fork never exec'd: /proc shows the server's environment, not the run's mark; the server's mark counts.
    app = App(unique_name("fork_stray"))
    app.add_task("dies", ForksThenDies(str(tmp_path / "child.pid")), period_ns=2_000_000, policy="other")
    with pytest.raises(TaskFailed):
        rtloop.run(app, 2.0, tmp_path / "out")
    child = int((tmp_path / "child.pid").read_text())
    assert _gone_within(child, 5), "the task's own child outlived the run"
    assert _alive(task_start.server_pid() or 0), "the run ended the task server (it serves the next run)"


APP = """name = "{name}"
[tasks.ctl]
runnable = "device_test_drivers:Echo"
period_ns = 2_000_000
priority = 10
[devices.dev]
kind = "device_test_drivers:LogDevice"
task = "ctl"
log = "{log}"
[devices.dev.limits.c0]
min = -1e6
max = 1e6
safe = -7.0
[[connect]]
from = "ctl.y[0]"
to = "dev.u[0]"
[[connect]]
from = "dev.y[0]"
to = "ctl.u[0]"
"""


def _parent(pid: int) -> int:
    with open(f"/proc/{pid}/stat") as stat:
        return int(stat.read().rsplit(")", 1)[1].split()[1])


def test_a_killed_supervisor_ends_its_task_with_safe_values_and_leaves_no_server(tmp_path: Path, forking: None) -> None:
    app = tmp_path / "app.toml"
    log = tmp_path / "dev.log"
    app.write_text(APP.format(name=unique_name("fork_kill9"), log=log))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    supervisor = subprocess.Popen([sys.executable, "-m", "rtloop", "run", str(app), "--out", str(tmp_path / "out")],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                                  env=env)
    task = server = 0
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not any(line.startswith("write ") for line in read_log(log)):
            time.sleep(0.1)  # the loop runs: its device is written every cycle
        task = int(Path(f"{log}.pid").read_text())
        server = _parent(task)
        assert server != supervisor.pid and _parent(server) == supervisor.pid, "the task was not forked from a server"
        supervisor.kill()  # SIGKILL: no orderly stop from the supervisor
        supervisor.wait()
        # the server sees the supervisor's end of its pipe close and ends; its end is the task's parent-death signal
        assert _gone_within(server, 10), "the task server outlived its supervisor"
        assert _gone_within(task, 10), "the task went on running its loop with no supervisor"
        assert read_log(log)[-3:] == ["safe -7.0", "deactivate", "close"], read_log(log)[-5:]
    finally:
        if supervisor.poll() is None:
            supervisor.kill()
            supervisor.wait()
        for pid in (task, server):
            if pid and _alive(pid):
                os.kill(pid, signal.SIGKILL)


def test_the_pages_the_server_holds_are_found_as_runs_of_present_pages() -> None:
    from array import array

    from rtloop.linux.lean import PAGE_BYTES, PRESENT, _present_runs

    entries = memoryview(array("Q", [PRESENT, PRESENT | 5, 0, PRESENT, 0, 0]).tobytes()).cast("Q")
    assert _present_runs(entries, 0x1000) == [(0x1000, 0x1000 + 2 * PAGE_BYTES),
                                              (0x1000 + 3 * PAGE_BYTES, 0x1000 + 4 * PAGE_BYTES)]
    assert _present_runs(memoryview(array("Q", [0, PRESENT]).tobytes()).cast("Q"), 0) == [(PAGE_BYTES, 2 * PAGE_BYTES)]


class _Process:
    def __init__(self, alive: bool) -> None:
        self.alive = alive

    def is_alive(self) -> bool:
        return self.alive


def test_t0_waits_for_a_bridge_until_it_says_ready_fails_or_dies() -> None:
    # Forked tasks are ready in ms, a bridge imports DDS for seconds: the supervisor's T0 waits for
    # "ready" (at most READY_WITHIN_S), as the spawned tasks' own start-up used to make it do.
    import multiprocessing

    from rtloop.app.specs import RosTopic
    from rtloop.runtime.bridges import Bridges, _Bridge

    bridges = Bridges.__new__(Bridges)
    reader, writer = multiprocessing.Pipe(duplex=False)
    topic = RosTopic.__new__(RosTopic)
    starting, dead = _Bridge(topic, _Process(True), reader), _Bridge(topic, _Process(False), multiprocessing.Pipe()[0])
    bridges.running = [starting, dead]
    assert bridges.starting()
    writer.send({"kind": "ready"})
    assert not bridges.starting() and starting.ready


def test_a_forked_copy_of_a_process_with_a_server_spawns_its_tasks(forking: None) -> None:
    # The server is its parent's child, not the copy's (multiprocessing's own check of it raised there).
    task_start.start_server()
    read_end, write_end = os.pipe()
    child = os.fork()
    if child == 0:
        try:
            context, server = task_start.task_context()
            os.write(write_end, f"{context.get_start_method()} {server}".encode())
        except BaseException as error:
            os.write(write_end, repr(error).encode())
        os._exit(0)
    os.close(write_end)
    os.waitpid(child, 0)
    with os.fdopen(read_end, "rb") as said:
        assert said.read().decode() == "spawn None"
