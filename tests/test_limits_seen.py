"""Limits that act are seen (issue 30, defects 3 and 4): what a device was sent is recorded beside the
controller's value and its clamps and rate-limited cycles are counted; a connection has the same
guard (min, max, rate_per_s), applied alike in run and simulate, by the C core and its Python twin."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

import rtloop
from conftest import unique_name
from device_test_drivers import MirrorTwin, read_log
from replay_helpers import compare_signals, first_miss_s
from rt_test_runnables import Counter, Gain
from rtloop import App
from rtloop.app.appfile import load_app
from rtloop.errors import AppError

PERIOD_NS = 2_000_000


def rows(out: Path) -> list[dict[str, float]]:
    with open(out / "signals.csv") as stream:
        return [{key: float(value) for key, value in row.items()} for row in csv.DictReader(stream)]


def summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def device_app(tmp_path: Path, name: str, rate_per_s: float | None = None) -> App:
    """``ctl`` asks for 22 every cycle; its device takes at most 10 (and, with ``rate_per_s``, moves slowly)."""
    app = App(unique_name(name))
    ctl = app.add_task("ctl", Gain(1, 0.0, 22.0), period_ns=PERIOD_NS)
    limit = {"min": -10.0, "max": 10.0, "safe": 0.0, **({"rate_per_s": rate_per_s} if rate_per_s else {})}
    dev = app.add_device("dev", "device_test_drivers:LogDevice", task="ctl", log=str(tmp_path / "dev.log"),
                         twin=MirrorTwin(1, 1.0), limits={"c0": limit})
    app.connect(ctl.y[0], dev.u[0])
    app.connect(dev.y[0], ctl.u[0])
    app.record(ctl.y)
    return app


def test_a_clamping_device_limit_is_recorded_counted_and_said(tmp_path: Path, hot_path: str) -> None:
    rtloop.simulate(device_app(tmp_path, "lim_dev_sim"), 0.1, tmp_path / "sim")
    table = rows(tmp_path / "sim")
    assert {row["ctl.y[0]"] for row in table[1:]} == {22.0}  # what the controller asked for
    # what the device was sent: at release 0 the controller's initial output (io = let), then 22 clamped
    assert table[0]["dev.c0"] == 0.0 and {row["dev.c0"] for row in table[1:]} == {10.0}
    assert [row["ctl.u[0]"] for row in table][:3] == [0.0, 10.0, 10.0]  # its twin read back what it was sent
    device = summary(tmp_path / "sim")["devices"]["dev"]
    assert device["clamped_cycles"] == {"c0": 49} and device["rate_limited_cycles"] == {}
    assert any("device 'dev': command c0 clamped to its min/max in 49 cycles" in note
               for note in summary(tmp_path / "sim")["notes"])


def test_a_rate_limit_is_counted_per_cycle_it_held_the_command_back(tmp_path: Path, hot_path: str) -> None:
    rtloop.simulate(device_app(tmp_path, "lim_rate_sim", rate_per_s=1000.0), 0.1, tmp_path / "sim")  # 2 per cycle
    sent = [row["dev.c0"] for row in rows(tmp_path / "sim")]
    assert sent[:7] == [0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 10.0]
    device = summary(tmp_path / "sim")["devices"]["dev"]
    assert device["rate_limited_cycles"] == {"c0": 4} and device["clamped_cycles"] == {"c0": 49}


def test_the_report_draws_what_was_sent_beside_what_was_asked_and_marks_where_a_limit_acted(tmp_path: Path) -> None:
    from rtloop.record.load import load
    from rtloop.report.signals import groups_of, signals_figure

    rtloop.simulate(device_app(tmp_path, "lim_report", rate_per_s=1000.0), 0.1, tmp_path / "sim")
    signals = load(tmp_path / "sim").signals
    group = groups_of(signals)[0]
    assert group.limits and group.names == ("ctl.y[0]", "dev.c0") and group.setpoint == "ctl.y[0]"
    figure = signals_figure("sim", signals)
    assert "red: a limit acted (1 stretch(es))" in figure.get_suptitle()
    legend = [text.get_text() for text in figure.axes[0].get_legend().get_texts()]
    assert legend == ["ctl.y[0] (asked for)", "dev.c0", "limit acted"]
    from rtloop.report.signals import comparison_figure

    rtloop.simulate(device_app(tmp_path, "lim_report2", rate_per_s=1000.0), 0.1, tmp_path / "sim2")
    overlay = comparison_figure([("sim", signals, {}), ("sim2", load(tmp_path / "sim2").signals, {})])
    assert overlay is not None and "red: a limit acted in sim (1 stretch(es))" in overlay.get_suptitle()


def test_a_run_says_its_device_clamps_and_equals_its_simulation(tmp_path: Path) -> None:
    rtloop.simulate(device_app(tmp_path, "lim_dev_s", rate_per_s=1000.0), 0.2, tmp_path / "sim")
    rtloop.run(device_app(tmp_path, "lim_dev_r", rate_per_s=1000.0), 0.2, tmp_path / "run")
    run = summary(tmp_path / "run")
    assert run["devices"]["dev"]["clamped_cycles"]["c0"] >= 10
    assert run["devices"]["dev"]["rate_limited_cycles"] == {"c0": 4}
    assert any("command c0 clamped" in note and "signals.csv column dev.c0" in note for note in run["notes"])
    writes = [float(line.split()[1]) for line in read_log(tmp_path / "dev.log") if line.startswith("write ")]
    assert writes[:7] == [0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 10.0]  # the wire got what dev.c0 says
    miss_s = first_miss_s(tmp_path / "run")
    compared, difference = compare_signals(tmp_path / "run" / "signals.csv", tmp_path / "sim" / "signals.csv", miss_s)
    assert difference is None and compared >= 1


# --- defect 4: a connection's guard --------------------------------------------------------------------

def guarded_app(name: str, **guard: float) -> App:
    """``ctl`` asks for 22 (after 0 at T0, its initial output), ``plant`` reads it through a guarded connection."""
    app = App(unique_name(name))
    ctl = app.add_task("ctl", Gain(1, 0.0, 22.0), period_ns=PERIOD_NS)
    plant = app.add_task("plant", Gain(2, 1.0), period_ns=PERIOD_NS)
    app.connect(ctl.y[0:1], plant.u[0:1], **guard)
    app.record(ctl.y, plant.u)
    return app


def test_a_guarded_connection_clamps_and_rate_limits_in_c_and_in_python(tmp_path: Path, hot_path: str) -> None:
    rtloop.simulate(guarded_app("lim_conn", min=-10.0, max=10.0, rate_per_s=1500.0), 0.1, tmp_path / "sim")
    table = rows(tmp_path / "sim")
    force = [row["plant.u[0]"] for row in table]
    assert force[:8] == [0.0, 3.0, 6.0, 9.0, 10.0, 10.0, 10.0, 10.0]  # 0 at T0, then 22 held at 10, 3 a cycle
    assert {row["ctl.y[0]"] for row in table[1:]} == {22.0}
    limits = summary(tmp_path / "sim")["tasks"]["plant"]["input_limits"]
    assert limits == {"plant.u[0]": {"clamped_cycles": 49, "rate_limited_cycles": 3}}
    from rtloop.record.load import load
    from rtloop.report.signals import groups_of, signals_figure

    signals = load(tmp_path / "sim").signals
    first = groups_of(signals)[0]
    assert (first.names, first.limits) == (("ctl.y[0]", "plant.u[0]"), True)
    assert "red: a limit acted (1 stretch(es))" in signals_figure("sim", signals).get_suptitle()
    assert any("connection into plant.u[0]: clamped to its min/max in 49 cycles and held back by its "
               "rate_per_s in 3 cycles" in note for note in summary(tmp_path / "sim")["notes"])


def test_a_guarded_connection_runs_as_it_simulates(tmp_path: Path, hot_path: str) -> None:
    rtloop.simulate(guarded_app("lim_conn_s", min=-10.0, max=10.0, rate_per_s=1500.0), 0.2, tmp_path / "sim")
    rtloop.run(guarded_app("lim_conn_r", min=-10.0, max=10.0, rate_per_s=1500.0), 0.2, tmp_path / "run")
    miss_s = first_miss_s(tmp_path / "run")
    compared, difference = compare_signals(tmp_path / "run" / "signals.csv", tmp_path / "sim" / "signals.csv", miss_s)
    assert difference is None, f"run and simulation differ at t = {difference} s (first miss {miss_s})"
    assert compared >= 1
    limits = summary(tmp_path / "run")["tasks"]["plant"]["input_limits"]
    assert limits["plant.u[0]"]["rate_limited_cycles"] == 3 and limits["plant.u[0]"]["clamped_cycles"] >= 10
    assert rows(tmp_path / "run")[4]["plant.u[0]"] == 10.0
    from rtloop.runtime.replay import replay

    replayed = replay(tmp_path / "run", tmp_path / "replay",  # the replay goes through the same guard
                      guarded_app("lim_conn_p", min=-10.0, max=10.0, rate_per_s=1500.0))
    assert replayed.equal, replayed.divergence or replayed.cannot


def test_a_replayed_stale_read_goes_through_the_connections_guard(tmp_path: Path, hot_path: str) -> None:
    """A stale read on a guarded connection, replayed: the guard acts on the sample the run read, and its
    rate limit goes on from there, as in the run's loop. The stale read is written into the run's reads.csv
    (a simulation has none; a real one needs a loaded machine): at cycle 3 plant read ctl's initial 0.0
    (stamp 0) in place of the 22 due at 3P."""
    guard = {"min": -10.0, "max": 10.0, "rate_per_s": 1500.0}  # 3.0 per 2 ms cycle
    rtloop.simulate(guarded_app("lim_stale_s", **guard), 0.02, tmp_path / "run")
    with open(tmp_path / "run" / "reads.csv", "a") as file:
        file.write(f"plant,3,ctl,0,{3 * PERIOD_NS}\n")
    from rtloop.runtime.replay import replay

    replayed = replay(tmp_path / "run", tmp_path / "replay", guarded_app("lim_stale_p", **guard))
    force = [row["plant.u[0]"] for row in rows(tmp_path / "replay")]
    # 0.0 read at cycle 3 moves 3.0 down from 6.0 (not to 0.0, raw), then 22 held at 10 climbs back 3 a cycle
    assert force[:8] == [0.0, 3.0, 6.0, 3.0, 6.0, 9.0, 10.0, 10.0]
    assert replayed.divergence is not None  # the run read no stale sample: the replay says where it parts
    assert [name for name, *_ in replayed.divergence.signals] == ["plant.u[0]"]


def test_a_keep_window_replays_a_guarded_connection_from_where_its_rate_limit_stood(
        tmp_path: Path, hot_path: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A --keep run replayed from a task snapshot: the guard's rate limit goes on from the input the
    snapshot holds, not from the input's start value (the replay gave 0.5 where the run had 1080.0).
    ``ctl`` counts 1, 2, 3...; the connection lets plant's input climb 0.5 a cycle, far behind."""
    from rtloop.record import flight
    from rtloop.runtime.replay import replay

    monkeypatch.setattr(flight, "MIN_SEGMENT_NS", 250_000_000)  # 20 segments: the early ones are gone

    def counting_app(name: str) -> App:
        app = App(unique_name(name))
        ctl = app.add_task("ctl", Counter(), period_ns=PERIOD_NS)
        plant = app.add_task("plant", Gain(1, 1.0), period_ns=PERIOD_NS)
        app.connect(ctl.y[0:1], plant.u[0:1], rate_per_s=250.0)
        app.record(ctl.y, plant.u)
        return app

    rtloop.run(counting_app("lim_keep_r"), 5.0, tmp_path / "run", keep_s=0.5)
    result = replay(tmp_path / "run", tmp_path / "replay", counting_app("lim_keep_p"))
    assert result.from_s > 0, "the files no longer hold the run from t = 0: the replay starts from a snapshot"
    assert result.equal, result.divergence or result.cannot
    assert rows(tmp_path / "replay")[0]["plant.u[0]"] > 100.0


def test_an_app_file_connection_takes_min_max_and_rate_per_s(tmp_path: Path) -> None:
    text = f"""
name = "{unique_name('lim_file')}"
[tasks.ctl]
runnable = "rt_test_runnables:Gain"
args = {{ n = 1, gain = 0.0, offset = -22.0 }}
period_ns = {PERIOD_NS}
[tasks.plant]
runnable = "rt_test_runnables:Gain"
args = {{ n = 1 }}
period_ns = {PERIOD_NS}
[[connect]]
from = "ctl.y[0]"
to = "plant.u[0]"
min = -5
max = 5.0
[record]
signals = ["plant.u"]
"""
    (tmp_path / "app.toml").write_text(text)
    rtloop.simulate(load_app(tmp_path / "app.toml"), 0.02, tmp_path / "sim")
    assert {row["plant.u[0]"] for row in rows(tmp_path / "sim")[1:]} == {-5.0}
    (tmp_path / "bad.toml").write_text(text.replace("max = 5.0", "max = 1e308"))
    with pytest.raises(AppError, match=r"connect\[0\]: .*max must be a finite number within ±1e\+12, got 1e\+308"):
        load_app(tmp_path / "bad.toml")
    (tmp_path / "bad.toml").write_text(text.replace("max = 5.0", "max = -6.0"))
    with pytest.raises(AppError, match=r"need min ≤ max, got min -5\.0, max -6\.0"):
        load_app(tmp_path / "bad.toml")


def test_a_guard_is_refused_where_it_cannot_act(tmp_path: Path) -> None:
    app = device_app(tmp_path, "lim_refused")
    other = app.add_task("other", Gain(1), period_ns=PERIOD_NS)
    with pytest.raises(AppError, match="a NaN cannot be clamped"):
        app.connect(app.tasks["ctl"].y[0], other.u[0], max=1.0, allow_nonfinite=True)
    app2 = App(unique_name("lim_refused2"))
    ctl = app2.add_task("ctl", Gain(1), period_ns=PERIOD_NS)
    dev = app2.add_device("dev", "device_test_drivers:LogDevice", task="ctl", log=str(tmp_path / "d.log"),
                          limits={"c0": {"min": -1, "max": 1, "safe": 0}})
    with pytest.raises(AppError, match=r"the device's commands have theirs \(\[devices.dev.limits\]\)"):
        app2.connect(ctl.y[0], dev.u[0], max=0.5)


def test_the_python_guards_allocate_nothing_that_stays() -> None:
    """The Python twin of the connections' guard (and the devices' guard with its counts) keep no
    memory per cycle: 10,000 cycles, clamping and rate limiting every one."""
    from io_guest_devices import bytes_kept_by
    from rtloop.io.device import CommandLimit
    from rtloop.io.limits import CommandGuard
    from rtloop.ipc.wiring import InputGuards, InputLink

    u = np.zeros(4)
    guards = InputGuards([InputLink("w", slice(0, 2), slice(0, 2), PERIOD_NS, "w", -1.0, 1.0, 0.1)], u)

    def connection_cycle() -> None:
        u[0], u[1] = 5.0, -5.0 if u[1] > -0.5 else 5.0
        guards.apply()

    assert bytes_kept_by(connection_cycle, 10_000) < 1024
    assert guards.clamped.tolist() == [12_000, 12_000] and guards.rate_limited[0] == 10
    command = CommandGuard([CommandLimit(-1.0, 1.0, 0.0, 50.0)], PERIOD_NS, ["dev.u[0] (c0)"])
    wanted = np.array([3.0])

    def device_cycle() -> None:
        wanted[0] = -wanted[0]
        command.apply(wanted, "ctl", 0)

    assert bytes_kept_by(device_cycle, 10_000) < 1024
    assert command.clamped[0] == 12_000 and command.rate_limited_cycles[0] == 12_000
