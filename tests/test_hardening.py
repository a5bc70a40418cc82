"""Bad input is one clear line and exit 2; bounds hold before anything starts; small fixes of issue 11."""

from __future__ import annotations

import json
import math
import os
import re
import secrets
from pathlib import Path

import numpy as np
import pytest

import rtloop
from rtloop.app.appfile import load_app
from rtloop.app.builder import App
from rtloop.app.specs import MAX_DURATION_S, check_duration
from rtloop.cli.main import main
from rtloop.errors import AppError, PortValueError
from rtloop.ipc.ports import connect_app
from rtloop.ipc.values import validate_values
from rtloop.record.csvfiles import _csv_block
from rtloop.record.recorder import give_to_invoking_user
from rtloop.ros.bridge import narrowest_range
from rtloop.ros.validate import MessageValidator
from rtloop.runtime.layout import AppLayout, check_memory, shared_memory_bytes

GOOD_TASK = '[tasks.t]\nrunnable = "rt_test_runnables:Gain"\nargs = { n = 2 }\nperiod_ns = 1_000_000\n'


def _unique(prefix: str) -> str:
    return f"{prefix}_{os.getpid()}_{secrets.token_hex(2)}"  # this test run's, and this call's


def _cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    code = main(list(args))
    err = capsys.readouterr().err
    return code, err


def _write(tmp_path: Path, text: str | bytes, name: str = "app.toml") -> Path:
    path = tmp_path / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    return path


def _assert_one_clear_line(code: int, err: str, *needles: str) -> None:
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert len(lines[0]) < 700, f"message of {len(lines[0])} characters"
    for needle in needles:
        assert needle in lines[0], err


# --- 4. every load-time failure: one line naming file, key or module, exit 2 ---------------------
def _module(tmp_path: Path, body: str) -> str:
    name = _unique("mod")
    (tmp_path / f"{name}.py").write_text(body)
    return name


CASES = {
    "undecodable": (b'name = "x"\n\xff\xfe\n', "not UTF-8"),
    "not toml": ("name = \n", "not valid TOML"),
    "syntax error": ("SYNTAX", "failed to import: SyntaxError"),
    "raises at import": ("IMPORT", "failed to import: KeyError"),
    "constructor raises": ("CTOR", "tasks.t.args"),
    "period overflow": ('name = "x"\n[tasks.t]\nrunnable = "rt_test_runnables:Noop"\nperiod_ns = 9223372036854775807\n',
                        "tasks.t: task 't': period_ns must be an integer from 10000"),
    "huge args": ('name = "x"\n[tasks.t]\nrunnable = "rt_test_runnables:Gain"\nargs = { n = "' + "x" * 500_000
                  + '" }\nperiod_ns = 1000000\n', "xxx…xxx"),
    "capacity float": ('name = "x"\n' + GOOD_TASK + '[ports.p]\nsource = "t.y"\ncapacity = 1e12\n',
                       "ports.p.capacity: expected an integer"),
    "capacity huge": ('name = "x"\n' + GOOD_TASK + '[ports.p]\nsource = "t.y"\ncapacity = 1000000000000\n',
                      "capacity must be an integer from 2 to"),
    "vector huge": ('name = "x"\n[tasks.t]\nrunnable = "rt_test_runnables:Gain"\nargs = { n = 1000000000 }\n'
                    "period_ns = 1000000\n", "n_inputs must be an integer from 0 to 65536"),
    "range reversed": ('name = "x"\n' + GOOD_TASK + '[ports.p]\nto = "t.u"\nrange = [1.0, -1.0]\n',
                       "ports.p: port 'p': range [1.0, -1.0] must be finite with lo ≤ hi"),
    "long name": (f'name = "{"n" * 100}"\n' + GOOD_TASK, "at most 32"),
    "tasks not a table": ('name = "x"\ntasks = 3\n', "tasks: expected a table"),
    "nested arrays": ('name = "x"\nx = ' + "[" * 5000 + "]" * 5000 + "\n", "not valid TOML: nested too deeply"),
    "nested dotted keys": ('name = "x"\n[tasks.t]\nrunnable = "rt_test_runnables:Gain"\nperiod_ns = 1000000\n'
                           "parameters = { " + ".".join(["a"] * 5000) + " = 1 }\n",
                           "tasks: nested too deeply (more than 32 levels"),
    "nested inline tables": ('name = "x"\n[tasks.t]\nrunnable = "rt_test_runnables:Gain"\nperiod_ns = 1000000\n'
                             "args = " + "{ a = " * 40 + "1" + " }" * 40 + "\n", "tasks: nested too deeply"),
    "lock_blas_buffer not a bool": ('name = "x"\n' + GOOD_TASK + 'lock_blas_buffer = "yes"\n',
                                    "tasks.t.lock_blas_buffer: expected true or false"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_load_time_failures_are_one_line_and_exit_2(case: str, tmp_path: Path, capsys) -> None:
    text, needle = CASES[case]
    if text == "SYNTAX":
        text = f'name = "x"\n[tasks.t]\nrunnable = "{_module(tmp_path, "def (:")}:C"\nperiod_ns = 1000000\n'
    elif text == "IMPORT":
        text = f'name = "x"\n[tasks.t]\nrunnable = "{_module(tmp_path, "{}[1]")}:C"\nperiod_ns = 1000000\n'
    elif text == "CTOR":
        body = ("from rtloop import Runnable\nclass C(Runnable):\n    n_inputs = n_outputs = 0\n"
                "    def __init__(self):\n        raise ValueError('no hardware')\n"
                "    def step(self, u, y):\n        pass\n")
        text = f'name = "x"\n[tasks.t]\nrunnable = "{_module(tmp_path, body)}:C"\nperiod_ns = 1000000\n'
    path = _write(tmp_path, text)
    code, err = _cli(capsys, "simulate", str(path), "--duration", "0.01", "--out", str(tmp_path / "out"))
    _assert_one_clear_line(code, err, str(path), needle)


def test_a_directory_as_app_file(tmp_path: Path, capsys) -> None:
    code, err = _cli(capsys, "run", str(tmp_path), "--duration", "1", "--out", str(tmp_path / "out"))
    _assert_one_clear_line(code, err, "is a directory")


@pytest.mark.parametrize("duration", ["inf", "nan", "1e12", "-1", "0"])
def test_duration_out_of_range(duration: str, tmp_path: Path, capsys) -> None:
    path = _write(tmp_path, 'name = "x"\n' + GOOD_TASK)
    code, err = _cli(capsys, "run", str(path), "--duration", duration, "--out", str(tmp_path / "out"))
    _assert_one_clear_line(code, err, "duration must be more than 0 and at most")
    with pytest.raises(AppError):
        rtloop.simulate(load_app(path), float(duration), tmp_path / "out")


def test_check_duration_bounds() -> None:
    assert check_duration(MAX_DURATION_S) == MAX_DURATION_S
    for bad in (0, -1.0, math.inf, math.nan, MAX_DURATION_S * 2, True, "1"):
        with pytest.raises(AppError):
            check_duration(bad)  # type: ignore[arg-type]


def test_debug_shows_the_traceback(tmp_path: Path, capsys) -> None:
    body = "raise KeyError('boom')\n"
    path = _write(tmp_path, f'name = "x"\n[tasks.t]\nrunnable = "{_module(tmp_path, body)}:C"\nperiod_ns = 1000000\n')
    code, err = _cli(capsys, "--debug", "simulate", str(path), "--duration", "0.01", "--out", str(tmp_path / "o"))
    assert code == 2 and "Traceback" in err and "KeyError: 'boom'" in err


# --- 3. shared memory bounds --------------------------------------------------------------------
def test_shared_memory_is_checked_against_dev_shm_and_memlock_before_anything_starts(tmp_path: Path) -> None:
    from rt_test_runnables import Gain

    app = App(_unique("mem"))
    task = app.add_task("t", Gain(65536), period_ns=1_000_000)
    app.record(task.y)  # a record queue of 32768 ticks × 131072 values: 34 GB
    assert shared_memory_bytes(app) > 30e9
    with pytest.raises(AppError, match=r"needs 34\d{3}\.\d MB of shared memory; /dev/shm has"):
        rtloop.simulate(app, 0.01, tmp_path / "out")
    assert not list(Path("/dev/shm").glob(f"rtloop-{app.name}-*"))
    small = App(_unique("mem"))
    small.add_task("t", Gain(2), period_ns=1_000_000)
    needed = check_memory(small, memlock_limit_bytes=1 << 40)
    with pytest.raises(AppError, match="above RLIMIT_MEMLOCK"):
        check_memory(small, memlock_limit_bytes=needed - 1)


def test_shared_memory_estimate_matches_what_is_created() -> None:
    from rt_test_runnables import Counter, Gain

    app = App(_unique("size"))
    a = app.add_task("a", Counter(), period_ns=1_000_000)
    b = app.add_task("b", Gain(2), period_ns=1_000_000)
    app.connect(a.y, b.u)
    app.port("out", source=b.y, capacity=100)
    app.record(a.y)
    layout = AppLayout.create(app)
    try:
        created = sum(segment.size_bytes for segment in layout.segments)
    finally:
        layout.close()
    assert created == shared_memory_bytes(app)


# --- 5. ranges -----------------------------------------------------------------------------------
def test_port_range_rejects_values_outside_like_nan(tmp_path: Path) -> None:
    name = _unique("ranged")
    path = _write(tmp_path, f'name = "{name}"\n' + GOOD_TASK + '[ports.set]\nto = "t.u"\nrange = [-1, 1]\n')
    app = load_app(path)
    assert app.ports["set"].value_range == (-1.0, 1.0)
    layout = AppLayout.create(app)
    try:
        running = connect_app(name)
        running.write("set", [0.5, -1.0])
        for bad in ([1e308, 0.0], [0.0, -1.5], [math.nan, 0.0]):
            with pytest.raises(PortValueError):
                running.write("set", bad)
        assert layout.input_ports["set"].writes == 1
    finally:
        layout.close()


def test_a_range_per_value_bounds_each_value_of_the_port_on_its_own(tmp_path: Path) -> None:
    name = _unique("ranged2")
    path = _write(tmp_path, f'name = "{name}"\n' + GOOD_TASK +
                  '[ports.set]\nto = "t.u"\nrange = [[0, 0.5], [0, 20]]\n')
    app = load_app(path)
    assert app.ports["set"].value_range == ((0.0, 0.0), (0.5, 20.0))
    layout = AppLayout.create(app)
    try:
        running = connect_app(name)  # the range goes through the registry to every writer
        running.write("set", [0.5, 20.0])
        for bad, message in (([1e308, 4.0], r"1e\+308 at index 0 .* range \[0.0, 0.5\]"),
                             ([0.1, 25.0], r"25.0 at index 1 .* range \[0.0, 20.0\]")):
            with pytest.raises(PortValueError, match=message):
                running.write("set", bad)
        assert layout.input_ports["set"].writes == 1
    finally:
        layout.close()
    assert narrowest_range(((0.0, 0.0), (0.5, 20.0)), (-1.0, 10.0)) == ((0.0, 0.0), (0.5, 10.0))
    for wrong, said in (("[[0, 1]]", "1 [lo, hi] pairs, the port has 2"), ("[[0, 1], [2, 1]]", "lo ≤ hi"),
                        ("[[0, 1], 5]", "range must hold numbers"),
                        ("[1, 2, 3]", "range must be [lo, hi] or one [lo, hi] per value")):
        path.write_text(f'name = "{name}"\n' + GOOD_TASK + f'[ports.set]\nto = "t.u"\nrange = {wrong}\n')
        with pytest.raises(AppError, match=re.escape(said)):
            load_app(path)


def test_validate_values_range() -> None:
    assert validate_values([1, 2], 2, value_range=(0, 2)).tolist() == [1.0, 2.0]
    with pytest.raises(PortValueError, match="outside its range"):
        validate_values([1, 3], 2, value_range=(0, 2))
    with pytest.raises(PortValueError, match="expected numbers"):
        validate_values(["x" * 10_000], 1)
    try:
        validate_values(["x" * 10_000], 1)
    except PortValueError as error:
        assert len(str(error)) < 200


def test_ros_subscription_range_is_checked_and_counted(tmp_path: Path) -> None:
    path = _write(tmp_path, 'name = "rr"\n' + GOOD_TASK + '[ports.set]\nto = "t.u"\nrange = [-2, 2]\n'
                  '[[ros.subscribe]]\ntopic = "/rr/set"\nport = "set"\nrange = [-1, 5]\n')
    topic = load_app(path).ros_topics[0]
    assert topic.value_range == (-1.0, 5.0)
    allowed = narrowest_range(topic.value_range, (-2.0, 2.0))
    assert allowed == (-1.0, 2.0)
    validator = MessageValidator(2, value_range=allowed, warner=None)
    assert validator.check([0.0, 2.0]) is not None
    assert validator.check([0.0, 2.5]) is None and validator.check([-1.5, 0.0]) is None
    assert validator.counts.rejected["range"] == 2 and validator.counts.accepted == 1


def test_csv_writes_nan_and_inf_as_python_reads_them() -> None:
    values = np.array([[math.nan, math.inf, -math.inf, 0.1]])
    line = _csv_block(np.array([1_500_000_000]), values, np.zeros(values.shape, dtype=bool))
    assert line == "1.5,nan,inf,-inf,0.1\n"
    assert math.isnan(float(line.split(",")[1]))


# --- 7. the small ones --------------------------------------------------------------------------
def test_port_read_starts_with_the_newest_sample_unless_asked_for_the_queue(tmp_path: Path, capsys) -> None:
    from rt_test_runnables import Counter

    app = App(_unique("reader"))
    task = app.add_task("c", Counter(), period_ns=1_000_000)
    app.port("out", source=task.y, capacity=64)
    layout = AppLayout.create(app)
    try:
        queue = layout.output_ports["out"]
        for tick in range(10):
            queue.push(tick, np.array([float(tick), 0.0]))
        assert main(["port", "read", app.name, "out", "--count", "1"]) == 0
        header, line = capsys.readouterr().out.splitlines()
        assert header.split() == ["t_s", "c.y[0]", "c.y[1]"]  # a header names the columns
        assert line.split()[1] == "9"  # now, not ten ticks ago
        for tick in range(10, 13):
            queue.push(tick, np.array([float(tick), 0.0]))
        assert main(["port", "read", app.name, "out", "--count", "2", "--queued"]) == 0
        lines = capsys.readouterr().out.splitlines()[1:]
        assert [line.split()[1] for line in lines] == ["10", "11"]
        assert len({len(line) for line in lines}) == 1  # fixed-width columns: nothing jumps
    finally:
        layout.close()


def test_chown_under_sudo_does_not_follow_links(tmp_path: Path, monkeypatch) -> None:
    if os.geteuid() != 0:
        pytest.skip("needs root: the chown under sudo runs as root")
    outside = tmp_path / "not-an-artifact"
    outside.write_text("root's")
    out = tmp_path / "out"
    out.mkdir()
    (out / "summary.json").write_text("{}")
    (out / "planted").symlink_to(outside)
    monkeypatch.setenv("SUDO_UID", "65534")
    monkeypatch.setenv("SUDO_GID", "65534")
    give_to_invoking_user(out)
    assert (out / "summary.json").stat().st_uid == 65534
    assert (out / "planted").lstat().st_uid == 65534
    assert outside.stat().st_uid == 0


def test_summary_says_whether_cpu_dma_latency_was_held(tmp_path: Path) -> None:
    from rt_test_runnables import Noop

    app = App(_unique("dma"))
    app.add_task("t", Noop(), period_ns=1_000_000, policy="other")
    rtloop.run(app, 0.2, tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    try:
        os.close(os.open("/dev/cpu_dma_latency", os.O_WRONLY))
        can_hold = True
    except OSError:
        can_hold = False
    assert summary["machine"]["cpu_dma_latency_held"] is can_hold


def test_port_write_mistakes_are_said_in_plain_words() -> None:
    from rt_test_runnables import Gain
    from rtloop.ipc.ports import connect_app

    app = App(_unique("writer"))
    task = app.add_task("g", Gain(1), period_ns=1_000_000)
    app.port("setpoint", to=task.u[0], value_range=(-1.0, 1.0))
    layout = AppLayout.create(app)
    try:
        running = connect_app(app.name)
        with pytest.raises(PortValueError, match=r"takes 1 value, got 2$"):
            running.write("setpoint", [0.1, 0.2])
        with pytest.raises(PortValueError, match=r"value 7\.0 at index 0 is outside its range \[-1\.0, 1\.0\]$"):
            running.write("setpoint", np.array([7.0]))
        with pytest.raises(PortValueError, match=r"has no port 'setpiont'; did you mean 'setpoint'\?"):
            running.write("setpiont", [0.1])
    finally:
        layout.close()
