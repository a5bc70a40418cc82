from __future__ import annotations

import fcntl
import importlib.util
import json
import os
import random
import subprocess
import sys
import time
import tomllib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from hypothesis import settings

from rtloop.linux import rt

# Property tests draw the same examples on every run (derandomized), so a red run on any
# machine, CI's included, reproduces with the same command. HYPOTHESIS_PROFILE=explore
# draws fresh random examples (and keeps failures in .hypothesis/) when hunting for new ones.
settings.register_profile("reproducible", derandomize=True, database=None, print_blob=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "reproducible"))

TESTS_DIR = Path(__file__).parent
sys.path.insert(0, str(TESTS_DIR))  # rt_test_runnables, for spawned task processes too
sys.path.insert(1, str(TESTS_DIR.parent / "examples" / "jiwy"))  # the JIWY example's plant and controller


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not in_rtkernel_guest():
        skip_guest = pytest.mark.skip(reason=f"runs in the PREEMPT_RT test guest only: {GUEST_COMMAND}")
        for item in items:
            if "rtkernel" in item.keywords:
                item.add_marker(skip_guest)
    capabilities = rt.probe()
    if capabilities.may_use_rt:
        return
    skip = pytest.mark.skip(reason=f"needs real-time scheduling: {capabilities.rt_reason}")
    for item in items:
        if "rt" in item.keywords:
            item.add_marker(skip)


# --- the PREEMPT_RT test guest (tools/rtkernel-vm.sh, docs/rtkernel-guest.md) ---------------------
GUEST_COMMAND = 'tools/rtkernel-vm.sh .venv/bin/python -m pytest -m "rt or rtkernel"'
SLOWDOWN_ENV = "RTLOOP_TEST_SLOWDOWN"


def in_rtkernel_guest() -> bool:
    """True when the suite runs in the guest: its init sets RTLOOP_GUEST=1 and writes the device map."""
    return os.environ.get("RTLOOP_GUEST") == "1" and bool(os.environ.get("RTLOOP_GUEST_DEVICES"))


def require_nobody_can_import_rtloop() -> None:
    """Skip when user 'nobody' (uid 65534) cannot import rtloop here: the checkout or its .venv lies
    under a folder only root may enter (``mktemp -d`` makes such a folder)."""
    probe = subprocess.run(["setpriv", "--reuid", "65534", "--regid", "65534", "--clear-groups", sys.executable,
                            "-c", "import rtloop"], capture_output=True, text=True, timeout=60)
    if probe.returncode != 0:
        pytest.skip("another local user cannot import rtloop here (installed under a folder only root may enter): "
                    f"{probe.stderr.strip().splitlines()[-1:]}")


def guest_device_map() -> dict:
    """The guest's device map (``/run/rtloop-guest/devices.json``); skips the test outside the guest."""
    if not in_rtkernel_guest():
        pytest.skip(f"runs in the PREEMPT_RT test guest only: {GUEST_COMMAND}")
    path = Path(os.environ["RTLOOP_GUEST_DEVICES"])
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as error:  # in the guest without its map: the guest is broken, fail
        pytest.fail(f"the guest's device map {path} is unreadable: {error}")


def guest_device(name: str) -> dict:
    """One device of the guest's map (``vcan``, ``can``, ``i2c``, ``uinput``, ``gpio``, ``spi``, ``serial``).

    Skips the test outside the guest, and in the guest when the device is missing, with the
    guest's reason (the guest's own presence tests fail instead: tests/test_rtkernel_guest.py).
    """
    device = guest_device_map()["devices"].get(name)
    if device is None:
        pytest.skip(f"the guest's device map has no {name!r}")
    if not device["present"]:
        pytest.skip(f"{name} is missing in the guest: {device['reason']}")
    return device


def skip_in_rtkernel_guest(why: str) -> pytest.MarkDecorator:
    """A mark that skips a test in the guest only, saying why it cannot work there (it runs on the host)."""
    return pytest.mark.skipif(in_rtkernel_guest(), reason=f"not in the emulated PREEMPT_RT guest: {why}")


@pytest.fixture
def rtkernel_guest() -> dict:
    """The guest's device map (see docs/rtkernel-guest.md); the test is skipped outside the guest."""
    return guest_device_map()


def slowdown() -> float:
    """How many times slower than the host this machine runs Python: 1 here, ~20 in the emulated guest.

    The guest sets RTLOOP_TEST_SLOWDOWN. Real-time tests stretch their periods and durations by it
    (``scaled_ns``, ``scaled_s``) so that the same number of cycles runs and the same behaviour is
    asserted; nothing is asserted about time itself.
    """
    text = os.environ.get(SLOWDOWN_ENV, "1")
    try:
        factor = float(text)
    except ValueError:
        factor = float("nan")
    if not 1 <= factor <= 1000:  # also NaN
        raise pytest.UsageError(f"{SLOWDOWN_ENV}={text!r}: a factor from 1 to 1000 is expected")
    return factor


def scaled_ns(period_ns: int) -> int:
    """A period (or any interval in ns) stretched by this machine's slowdown."""
    return int(period_ns * slowdown())


def scaled_s(duration_s: float) -> float:
    """A duration (or timeout) in s stretched by this machine's slowdown."""
    return duration_s * slowdown()


@pytest.fixture
def rtloop_env() -> dict[str, str]:
    """Environment for running the rtloop CLI in a subprocess that finds the test runnables."""
    return cli_env()


def cli_env() -> dict[str, str]:
    """What the ``rtloop_env`` fixture gives, for fixtures of a wider scope."""
    env = dict(os.environ)
    paths = [str(TESTS_DIR), str(TESTS_DIR.parent / "examples" / "jiwy"), env.get("PYTHONPATH", "")]
    env["PYTHONPATH"] = os.pathsep.join(paths).rstrip(os.pathsep)
    return env


def unique_name(base: str) -> str:
    """An app name of this test run alone: apps are found by name, and other runs of this suite
    (another checkout, another user's CI job) may run the same test at the same time."""
    name = f"{base}_{os.getpid()}"
    assert len(name) <= 32, f"app names have at most 32 characters: {name!r}"
    return name


def worker_slot() -> tuple[int, int]:
    """This pytest-xdist worker's index (``gw0`` is 0) and how many workers the run has; (0, 1) in a
    serial run."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if not worker.startswith("gw"):
        return 0, 1
    return int(worker[2:]), max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))


def random_ros_domain() -> int:
    """A random ``ROS_DOMAIN_ID`` for one test, from 1 to 101 (ROS 2's range; 0 is the default, avoided).
    The workers of a parallel run draw from sets of their own, so two tests running at once never
    share a domain."""
    index, count = worker_slot()
    return random.Random(os.getpid() ^ time.monotonic_ns()).choice(range(1 + index, 102, count))


def private_ros_domain() -> str:
    """A ``ROS_DOMAIN_ID`` (0-232) of this test run's own, so bridges of apps run elsewhere on the
    machine (the JIWY example publishes on the default domain 0) neither see nor feed ours."""
    return str(1 + os.getpid() % 232)


def wait_for_app(name: str, process: subprocess.Popen, timeout_s: float = 60.0):
    """The running app ``name`` whose supervisor is ``process`` (``rtloop run`` started by the test);
    fails with the process's stderr at once if it ended instead."""
    from rtloop.ipc.ports import running_apps

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for app in running_apps():
            if app.name == name and app.pid == process.pid:
                return app
        if process.poll() is not None:
            pytest.fail(f"rtloop ended (exit {process.returncode}) before app {name!r} ran: {process.communicate()[1]}")
        time.sleep(0.05)
    pytest.fail(f"app {name!r} did not start within {timeout_s} s")


def wait_for_task_pids(app, process: subprocess.Popen, timeout_s: float = 60.0) -> dict[str, int]:
    """Every task process's pid, once all have started. Never a 0: ``os.kill(0, ...)`` would signal
    the test's own process group (pytest and whatever started it)."""
    deadline = time.monotonic() + timeout_s
    while not all((pids := app.task_pids()).values()):
        if process.poll() is not None:
            pytest.fail(f"rtloop ended (exit {process.returncode}) before its tasks started: "
                        f"{process.communicate()[1]}")
        if time.monotonic() > deadline:
            pytest.fail(f"not every task started within {timeout_s} s: {pids}")
        time.sleep(0.05)
    return pids


def wait_for_the_task_pid(app_file: Path, process: subprocess.Popen, timeout_s: float = 30.0) -> int:
    """The task process of a one-task app file that ``process`` (``rtloop run``) runs, from the app's registry."""
    name = tomllib.loads(app_file.read_text())["name"]
    (pid,) = wait_for_task_pids(wait_for_app(name, process, timeout_s), process, timeout_s).values()
    return pid


def wait_for_cycles(app, task: str, cycles: int, process: subprocess.Popen, timeout_s: float = 60.0) -> int:
    """Until ``task`` of the running ``app`` has computed ``cycles`` cycles (however loaded the machine).

    Returns how many it has computed. The status block holds the last cycle computed (0 before the
    first too: its execution time tells)."""
    from rtloop.ipc.status import STATUS_WORDS, StatusWord, WordBlock

    status = WordBlock(app.segment(app.registry["tasks"][task]), 0, STATUS_WORDS)
    deadline = time.monotonic() + timeout_s
    while (done := status[StatusWord.CYCLE] + 1 if status[StatusWord.EXEC_LAST_NS] > 0 else 0) < cycles:
        if process.poll() is not None:
            pytest.fail(f"rtloop ended (exit {process.returncode}) early: {process.communicate()[1]}")
        if time.monotonic() > deadline:
            pytest.fail(f"task {task!r} ran {done} cycles in {timeout_s} s, not {cycles}")
        time.sleep(0.02)
    return done


def layout_twins(fields: list, size: int, monkeypatch: pytest.MonkeyPatch) -> tuple:
    """The same ``ByteLayout`` twice: compiled (io/devio_c/bytelayout.c), and the Python reference."""
    from rtloop.io.bytelayout import ByteLayout

    pytest.importorskip("rtloop.io._devio", reason="the devices' C part was not built (no compiler)")
    compiled = ByteLayout(fields, size, "frame")
    monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
    reference = ByteLayout(fields, size, "frame")
    monkeypatch.delenv("RTLOOP_PURE_PYTHON")
    assert compiled._compiled is not None and reference._compiled is None
    return compiled, reference


def other_cpu() -> int:
    """A CPU to pin test tasks to: the last one."""
    return max(os.sched_getaffinity(0))


def find_cyclonedds_cli() -> str | None:
    """The ``cyclonedds`` command: beside this Python first (a venv's scripts are not on sudo's PATH)."""
    import shutil

    beside_python = Path(sys.executable).parent / "cyclonedds"
    return str(beside_python) if beside_python.exists() else shutil.which("cyclonedds")


@pytest.fixture(params=["c", "python"])
def hot_path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run the test under the compiled hot path and under its Python twin (task processes inherit it)."""
    from rtloop.ipc import hotpath

    if request.param == "c":
        monkeypatch.delenv(hotpath.PURE_PYTHON_ENV, raising=False)
        if not hotpath.c_built():
            pytest.skip(f"the C hot path is not available: {hotpath.why_python()}")
    else:
        monkeypatch.setenv(hotpath.PURE_PYTHON_ENV, "1")
    return request.param



@pytest.fixture(autouse=True)
def _apps_run_under_names_of_their_own(request: pytest.FixtureRequest,
                                       monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Fails a test that runs an app in real time, in this process, under a name without this run's
    pid (``unique_name``): a live app holds its name, and the same test of another run of the suite
    on this machine would be refused, or would refuse ours. (Apps a test starts with ``rtloop run``
    in a subprocess are named the same way; this check sees the runs of this process.)"""
    from rtloop.runtime import layout

    refuse = layout.refuse_if_running
    fixed: list[str] = []

    def checked(name: str, this_pid: int | None = None) -> None:
        if str(os.getpid()) not in name and name not in fixed:
            fixed.append(name)
        refuse(name, this_pid)

    monkeypatch.setattr(layout, "refuse_if_running", checked)
    yield
    if fixed:
        pytest.fail(f"{request.node.nodeid} ran app {fixed[0]!r} under a fixed name: use unique_name() "
                    "(tests/conftest.py), apps here hold their name while they run", pytrace=False)


# --- running in parallel (pytest-xdist: `--numprocesses` in pyproject.toml's addopts) --------------
# Most tests sleep through real-time runs, so the suite runs on every core at once. A test that
# measures the machine itself (latencies, misses, a SCHED_FIFO hog, locked memory, system-wide
# scans of /dev/shm, /proc or processes) is marked `alone`: it waits until no other test of this
# run is running, and no other test starts until it ends.
ALONE_LOCK_NAME = "rtloop-tests-alone.lock"


def pytest_addoption(parser: pytest.Parser, pluginmanager: pytest.PytestPluginManager) -> None:
    """Without pytest-xdist (a .venv made before it joined the test extra, or ``-p no:xdist``), the
    options pyproject.toml's addopts give it are taken and ignored: the suite runs serially."""
    if pluginmanager.has_plugin("xdist"):
        return
    if (importlib.util.find_spec("xdist") is not None and not pluginmanager.is_blocked("xdist")
            and not os.environ.get("PYTEST_DISABLE_PLUGIN_AUTOLOAD")):
        return  # it loads after this file (``-p conftest``) and adds the options itself
    group = parser.getgroup("xdist-absent", "pytest-xdist is not loaded: the tests run serially")
    group.addoption("--numprocesses", default=None, help="ignored: pytest-xdist is not loaded")
    group.addoption("--dist", default="no", help="ignored: pytest-xdist is not loaded")


def pytest_report_header(config: pytest.Config) -> str | None:
    if config.pluginmanager.has_plugin("xdist"):
        return None
    if importlib.util.find_spec("xdist") is None:
        return "rtloop: pytest-xdist is not installed, the tests run serially (pip install -e '.[test]' adds it)"
    return "rtloop: pytest-xdist is not loaded, the tests run serially"


def alone_lock_folder(config: pytest.Config) -> Path | None:
    """The folder of this run's lock, the same for all its workers: the controller's base temporary
    folder, which xdist makes each worker's basetemp a child of. None outside an xdist worker, where
    one test runs at a time anyway."""
    if "PYTEST_XDIST_WORKER" not in os.environ or not config.option.basetemp:
        return None
    return Path(config.option.basetemp).parent


@contextmanager
def machine_share(folder: Path | None, alone: bool) -> Iterator[None]:
    """Holds this run's lock, exclusive for an `alone` test, shared for any other, from the test's
    set-up to its tear-down. A turnstile lock taken around the request keeps a steady stream of
    shared holders from starving the exclusive one."""
    if folder is None:
        yield
        return
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / ALONE_LOCK_NAME, "a") as lock, open(folder / (ALONE_LOCK_NAME + ".turnstile"), "a") as gate:
        fcntl.flock(gate, fcntl.LOCK_EX)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        finally:
            fcntl.flock(gate, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    with machine_share(alone_lock_folder(item.config), alone=item.get_closest_marker("alone") is not None):
        return (yield)
