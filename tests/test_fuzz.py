"""Fuzzing: hypothesis-generated app files and port values.

Every case ends as a valid app or an :class:`~rtloop.errors.AppError` (the CLI's exit 2),
never another exception; a few valid ones are simulated through the CLI, which must exit
0 or 2 with no traceback and leave no shared memory behind.

The examples are drawn the same on every run (tests/conftest.py). Their counts are sized by
the lines of ``src/rtloop`` they reach: 400 generated and 400 mutated files reach every line
that 800 of each did, with the ``@example`` cases below (a constructor that raises, a bad app
name, a bad recorded signal: the paths the 800 found and 400 alone did not).
"""

from __future__ import annotations

import contextlib
import io
import math
import secrets
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from rtloop.app.appfile import load_app
from rtloop.cli.main import main
from rtloop.errors import AppError, PortValueError
from rtloop.ipc.values import validate_values
from rtloop.runtime.layout import check_memory

FUZZ = settings(deadline=None, suppress_health_check=list(HealthCheck), database=None)


# --- a tiny TOML writer (tomllib only reads) --------------------------------------------------------
def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value == math.inf else "-inf" if value == -math.inf
                                                else repr(value))
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items()) + " }"
    raise TypeError(value)


def _toml_key(key: str) -> str:
    return key if key.replace("_", "").isalnum() and key.isascii() else _toml_value(key)


def to_toml(data: dict[str, Any]) -> str:
    lines = [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for key, value in data.items():
        if isinstance(value, dict):
            for name, table in value.items():
                lines.append(f"[{_toml_key(key)}.{_toml_key(name)}]")
                if isinstance(table, dict):
                    lines += [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in table.items()]
                else:
                    lines[-1] = f"{_toml_key(key)}.{_toml_key(name)} = {_toml_value(table)}"
    return "\n".join(lines) + "\n"


# --- strategies --------------------------------------------------------------------------------
names = st.one_of(st.sampled_from(["a", "b", "plant", "controller", "x" * 40]), st.text(max_size=12))
numbers = st.one_of(
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, 1, 2, 10_000, 1_000_000, 2**31, 2**62, 1e12, -1]),
)
scalars = st.one_of(numbers, st.booleans(), st.text(max_size=20))
RUNNABLES = ["rt_test_runnables:Gain", "rt_test_runnables:Counter", "rt_test_runnables:Noop",
             "rt_test_runnables:Nothing", "no_such_module:X", "rt_test_runnables", ":", "os:getcwd",
             "rt_test_runnables:Fault"]
signals = st.one_of(
    st.builds(lambda t, s, a, b: f"{t}.{s}[{a}:{b}]", st.sampled_from(["a", "b", "zz"]), st.sampled_from("uyx"),
              st.integers(0, 4), st.integers(0, 5)),
    st.builds(lambda t, s: f"{t}.{s}", st.sampled_from(["a", "b"]), st.sampled_from("uy")),
    st.text(max_size=15),
)


def task_table() -> st.SearchStrategy[dict[str, Any]]:
    return st.fixed_dictionaries(
        {"runnable": st.one_of(st.sampled_from(RUNNABLES), scalars)},
        optional={
            "args": st.one_of(st.fixed_dictionaries({}, optional={"n": numbers, "gain": numbers}),
                              st.dictionaries(st.text(max_size=5), scalars, max_size=2)),
            "period_ns": st.one_of(numbers, st.just(1_000_000)),
            "priority": numbers, "cpu": numbers, "policy": st.sampled_from(["fifo", "other", "rr", "x", "deadline"]),
            "overrun": st.sampled_from(["skip", "catch_up", "later"]),
            "model": st.sampled_from(["20sim:nowhere", "fmu:nothing.fmu", "x"]),
            "bogus": scalars,
        },
    )


def port_table() -> st.SearchStrategy[dict[str, Any]]:
    return st.fixed_dictionaries(
        {},
        optional={
            "to": signals, "source": signals, "initial": st.lists(numbers, max_size=3),
            "allow_nonfinite": st.booleans(), "capacity": numbers, "range": st.lists(numbers, max_size=3),
            "feed": st.text(max_size=8), "description": scalars,
        },
    )


apps = st.fixed_dictionaries(
    {"name": st.one_of(st.just("fuzz"), names, scalars),
     "tasks": st.one_of(st.dictionaries(st.sampled_from(["a", "b"]), task_table(), min_size=1, max_size=2),
                        st.dictionaries(names, task_table(), max_size=2))},
    optional={
        "ports": st.dictionaries(st.sampled_from(["p", "q", "bad name"]), port_table(), max_size=2),
        "connect": st.lists(st.fixed_dictionaries({"from": signals, "to": signals}), max_size=2),
        "record": st.fixed_dictionaries({}, optional={"signals": st.lists(signals, max_size=2)}),
        "extra": scalars,
    },
)


def _connect_lines(data: dict[str, Any]) -> str:
    connect = data.pop("connect", [])
    return "".join(f"[[connect]]\nfrom = {_toml_value(c['from'])}\nto = {_toml_value(c['to'])}\n" for c in connect)


def _load_or_refuse(text: str, folder: Path) -> Any:
    """The app, or None when refused with an AppError (exit 2). Anything else fails the test."""
    path = folder / "fuzz.toml"
    path.write_text(text)
    try:
        app = load_app(path)
        app.validate()
        check_memory(app)
        return app
    except AppError:
        return None


@settings(FUZZ, max_examples=400)
@given(data=apps)
@example(data={"name": "fuzz", "tasks": {"a": {"runnable": "rt_test_runnables:Gain", "args": {"bogus": 1}}}})
def test_generated_app_files_load_or_are_refused_cleanly(data: dict[str, Any]) -> None:
    connect = _connect_lines(data)
    record = data.pop("record", None)
    text = to_toml(data) + connect + (f"[record]\nsignals = {_toml_value(record.get('signals', []))}\n"
                                      if record is not None else "")
    with tempfile.TemporaryDirectory() as folder:
        _load_or_refuse(text, Path(folder))


VALID = (
    'name = "fuzz"\n[tasks.a]\nrunnable = "rt_test_runnables:Gain"\nargs = { n = 2 }\nperiod_ns = 1_000_000\n'
    '[tasks.b]\nrunnable = "rt_test_runnables:Counter"\nperiod_ns = 2_000_000\n'
    '[[connect]]\nfrom = "b.y[0:2]"\nto = "a.u[0:2]"\n[ports.p]\nsource = "a.y"\ncapacity = 8\n'
    '[record]\nsignals = ["a.y"]\n'
)


@settings(FUZZ, max_examples=400)
@given(position=st.integers(0, len(VALID)), junk=st.text(max_size=6), cut=st.integers(0, 4))
@example(position=VALID.index("fuzz") + 2, junk=" ", cut=0)  # name = "fu zz"
@example(position=VALID.index('"a.y"]') + 3, junk="q", cut=0)  # signals = ["a.qy"]
def test_mutated_app_files_load_or_are_refused_cleanly(position: int, junk: str, cut: int) -> None:
    text = VALID[:position] + junk + VALID[position + cut:]
    with tempfile.TemporaryDirectory() as folder:
        _load_or_refuse(text, Path(folder))



@settings(FUZZ, max_examples=1000)
@given(values=st.one_of(
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4),
    st.lists(st.integers(), max_size=4),
    st.lists(st.one_of(st.text(max_size=3), st.none(), st.lists(st.floats(), max_size=2)), max_size=3),
    st.floats(), st.text(max_size=10),
), size=st.integers(1, 3), low=st.floats(-1e6, 1e6), width=st.floats(0, 1e6))
def test_port_values_are_valid_or_refused(values: Any, size: int, low: float, width: float) -> None:
    value_range = (low, low + width)
    try:
        array = validate_values(values, size, value_range=value_range)
    except PortValueError as error:
        assert len(str(error)) < 400
        return
    assert array.shape == (size,) and np.all(np.isfinite(array))
    assert np.all((array >= value_range[0]) & (array <= value_range[1]))


@settings(FUZZ, max_examples=6)
@given(n=st.integers(1, 4), period_ns=st.sampled_from([10_000, 1_000_000, 3_333_333]),
       capacity=st.integers(2, 64), duration_s=st.sampled_from([0.001, 0.01, 0.05, 1e9]))
def test_a_few_generated_apps_simulate_through_the_cli(n: int, period_ns: int, capacity: int,
                                                       duration_s: float) -> None:
    name = f"fuzz_{secrets.token_hex(3)}"
    text = (f'name = "{name}"\n[tasks.a]\nrunnable = "rt_test_runnables:Gain"\nargs = {{ n = {n} }}\n'
            f"period_ns = {period_ns}\n[ports.p]\nsource = \"a.y\"\ncapacity = {capacity}\n"
            '[record]\nsignals = ["a.y"]\n')
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "app.toml"
        path.write_text(text)
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main(["simulate", str(path), "--duration", repr(duration_s), "--out", f"{folder}/out", "-q"])
    assert code in (0, 2), err.getvalue()
    assert (code == 2) == (duration_s > 1e8), err.getvalue()
    assert "Traceback" not in err.getvalue()
    assert not list(Path("/dev/shm").glob(f"rtloop-{name}-*"))
