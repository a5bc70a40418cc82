"""``rtloop port list``: each port with its direction, signal and size, and the range and unit
its values take (one range per value, as the DC motor's gains declare, one line each), read
from the registry of a live app; a registry of the wrong shape is listed without a traceback."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import unique_name  # type: ignore[import-not-found]
from rtloop.app.appfile import load_app
from rtloop.cli.main import main
from rtloop.cli.port import describe_port
from rtloop.runtime.layout import AppLayout

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_the_dcmotor_example_lists_its_ranges_and_units(capsys: pytest.CaptureFixture[str]) -> None:
    app = load_app(EXAMPLES / "dcmotor" / "dcmotor.toml")
    app.name = unique_name("portlist")  # the registry a live app writes; no task is started
    layout = AppLayout.create(app, mode="simulate")
    try:
        assert main(["port", "list"]) == 0
    finally:
        layout.close()
    lines = capsys.readouterr().out.splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith(f"{app.name} (supervisor pid"))
    assert lines[header + 1:header + 7] == [
        "  setpoint         in   pi.u[1]  (1 value)  rad/s",
        "  load             in   plant.u[1]  (1 value)  range [-0.2, 0.2] N·m",
        "  gains            in   pi.u[2:4]  (2 values)",
        "      kp  range [0, 0.5] V·s/rad",
        "      ki  range [0, 20] V/rad",
        "  speed            out  plant.y[0]  (1 value)  rad/s",
    ]


def _port(**fields: object) -> dict[str, object]:
    return {"direction": "in", "signal": "c.u[2:4]", "size": 2, "range": None, **fields}


@pytest.mark.parametrize(("info", "lines"), [
    (_port(range=[-1.5, 1.5], units=["rad", "rad"]),
     ["  setpoint         in   c.u[2:4]  (2 values)  range [-1.5, 1.5] rad"]),
    (_port(range=[[0, -1e308], [0.5, 1e308]], names=["kp", ""]),  # unnamed values by index
     ["  setpoint         in   c.u[2:4]  (2 values)", "      kp   range [0, 0.5]",
      "      [1]  range [-1e+308, 1e+308]"]),
    (_port(units=["V", "A"], names=["volts", "amps"]),  # no range, a unit of its own each
     ["  setpoint         in   c.u[2:4]  (2 values)", "      volts  V", "      amps   A"]),
    (_port(range=[0, 1], units=["m", ""], names=["x", "y"]),
     ["  setpoint         in   c.u[2:4]  (2 values)", "      x  range [0, 1] m", "      y  range [0, 1]"]),
    (_port(), ["  setpoint         in   c.u[2:4]  (2 values)"]),  # a registry of an older rtloop
])
def test_one_line_for_a_shared_range_one_per_value_otherwise(info: dict[str, object], lines: list[str]) -> None:
    assert describe_port("setpoint", info) == lines


@pytest.mark.parametrize("info", [
    _port(range=[[0, 1, 2], [1, 2, 3]]), _port(range=["a", 1]), _port(range=[True, 1]), _port(range=[1]),
    _port(range={"lo": 0}), _port(units="rad", names=[1, 2]), _port(size="2"), _port(size=10**9), [], None,
])
def test_a_registry_of_the_wrong_shape_is_listed_without_what_is_wrong(info: object) -> None:
    lines = describe_port("setpoint", info)  # type: ignore[arg-type]
    assert lines[0].startswith("  setpoint ") and "range" not in "".join(lines)


def test_what_a_registry_says_is_made_printable() -> None:
    line, = describe_port("\x1b[2Jport", _port(size=1, signal="c.u[0]", units=["\x1b]0;owned\x07"]))
    assert "\x1b" not in line and "\x07" not in line and "?[2Jport" in line


class _FakeReader:
    period_ns = 1_000_000

    def __enter__(self) -> _FakeReader:
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def skip_to_newest(self) -> None:
        pass

    def read(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        return np.arange(count), np.zeros((count, 2))


@pytest.mark.parametrize("signal", ["\x1b]0;owned\x07.y[0:2]", 42])
def test_port_read_prints_a_registrys_signal_made_printable(signal: object, monkeypatch: pytest.MonkeyPatch,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    from rtloop.ipc import ports

    class App:
        ports = {"out": {"signal": signal}}  # noqa: RUF012

        def reader(self, _port: str) -> _FakeReader:
            return _FakeReader()

    monkeypatch.setattr(ports, "connect_app", lambda name, owner_uid=None: App())
    assert main(["port", "read", "app", "out", "--count", "2"]) == 0
    header, *rows = capsys.readouterr().out.splitlines()
    assert "\x1b" not in header and "\x07" not in header and header.lstrip().startswith("t_s") and len(rows) == 2
