"""Several controllers in one task: switch at a release, bumpless, in shadow; logged and replayed."""

from __future__ import annotations

import csv
import json
import math
import re
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import rtloop
from rtloop import App, Runnable
from rtloop.app.appfile import load_app
from rtloop.errors import AppError, AppFileError
from rtloop.runnable import TickInfo
from rtloop.switching import Controllers, switch_events

P = 1_000_000


class Pi(Runnable):
    """y = kp·e + ki·∫e, e = u[1] − u[0]; ``take_over`` sets the integral so y starts at y_last."""

    n_inputs, n_outputs = 2, 1
    output_names = ("command",)

    def __init__(self, kp: float, ki: float, bumpless: bool = True, ready: bool = True) -> None:
        self.kp, self.ki, self.bumpless, self.is_ready = kp, ki, bumpless, ready
        self.integral = 0.0
        self.steps = 0
        if not bumpless:
            self.take_over = None  # type: ignore[assignment]

    def ready(self) -> bool:
        return self.is_ready

    def take_over(self, u, y_last) -> None:
        error = u[1] - u[0]
        self.integral = (y_last[0] - self.kp * error) / self.ki

    def step(self, u, y) -> None:
        error = u[1] - u[0]
        self.integral += error * self.tick.period_ns * 1e-9
        y[0] = self.kp * error + self.ki * self.integral
        self.steps += 1


class Plant(Runnable):
    """A first-order lag (not at rest): x' = (command − x)/τ."""

    n_inputs, n_outputs = 1, 1
    output_names = ("x",)

    def __init__(self) -> None:
        self.x = 0.3
        self.initial_outputs = np.array([self.x])

    def step(self, u, y) -> None:
        self.x += (u[0] - self.x) * 0.02
        y[0] = self.x


def drive(controllers: Controllers, inputs: list[tuple[float, ...]]) -> np.ndarray:
    """Step ``controllers`` by hand through (measured, setpoint, controller, at_cycle, shadow) rows."""
    tick = TickInfo(period_ns=P)
    controllers.tick = tick
    u = np.zeros(controllers.n_inputs)
    u[:] = controllers.input_start_values
    controllers.bind_inputs(u)
    controllers.prerun()
    y = np.zeros(controllers.n_outputs)
    rows = []
    for cycle, row in enumerate(inputs):
        tick.cycle = cycle
        u[: len(row)] = row
        controllers.step(u, y)
        rows.append(y.copy())
    return np.array(rows)


def test_a_switch_acts_from_the_requested_release_and_take_over_makes_it_bumpless() -> None:
    controllers = Controllers({"fast": Pi(2.0, 5.0), "slow": Pi(0.5, 1.0)}, "fast")
    rows = [(0.1 * k / 100, 1.0, 0.0, 0.0, -1.0) for k in range(50)]
    rows += [(0.1 * k / 100, 1.0, 1.0, 60.0, -1.0) for k in range(50, 100)]  # asked at 50, from 60
    y = drive(controllers, rows)
    active = y[:, 1]
    assert active[59] == 0 and active[60] == 1 and list(active[60:]) == [1.0] * 40
    steps = np.abs(np.diff(y[:, 0]))
    normal = steps[40:58].max()
    assert steps[59] <= normal * 1.5 + 1e-12, "the output jumped at the switch"
    assert switch_events(active, controllers.names, P) == [
        {"cycle": 60, "t_s": 0.06, "from": "fast", "to": "slow"}]


def test_without_take_over_the_offset_decays_over_blend_s_and_the_first_output_equals_the_last() -> None:
    controllers = Controllers({"fast": Pi(2.0, 5.0), "slow": Pi(0.2, 0.1, bumpless=False)}, "fast", blend_s=0.01)
    rows = [(0.0, 1.0, 0.0, 0.0, -1.0)] * 20 + [(0.0, 1.0, 1.0, 20.0, -1.0)] * 30
    y = drive(controllers, rows)
    assert y[20, 0] == y[19, 0]  # the switch's first output is the last one: no bump
    plain = Pi(0.2, 0.1)
    plain.tick = TickInfo(period_ns=P)
    out = np.zeros(1)
    expected = []
    for _ in range(30):
        plain.step(np.array([0.0, 1.0]), out)
        expected.append(out[0])
    assert y[30:, 0] == pytest.approx(expected[10:], abs=1e-12)  # after 10 cycles (10 ms) the offset is gone
    assert abs(y[25, 0] - expected[5]) > 1e-3  # still blending half way


def test_a_controller_that_is_not_ready_is_refused_and_the_active_one_stays() -> None:
    controllers = Controllers({"a": Pi(1.0, 1.0), "b": Pi(1.0, 1.0, ready=False)}, "a")
    y = drive(controllers, [(0.0, 1.0, 1.0, 5.0, -1.0)] * 20)
    assert set(y[:, 1]) == {0.0}
    assert y[-1, 3] == 1  # one refusal, not one per cycle
    assert controllers.alternatives[1].steps == 0


def test_shadow_runs_beside_actuates_nothing_and_promotion_keeps_its_warm_state() -> None:
    active, candidate = Pi(1.0, 1.0), Pi(3.0, 2.0)
    controllers = Controllers({"a": active, "b": candidate}, "a")
    n_out = 1
    rows = [(0.0, 1.0, 0.0, 0.0, -1.0)] * 10 + [(0.0, 1.0, 0.0, 0.0, 1.0)] * 10 + [(0.0, 1.0, 1.0, 20.0, 1.0)] * 10
    y = drive(controllers, rows)
    reference = Pi(1.0, 1.0)
    reference.tick = TickInfo(period_ns=P)
    out = np.zeros(1)
    for k in range(20):
        reference.step(np.array([0.0, 1.0]), out)
        assert y[k, 0] == out[0]  # the actuated output is the active controller's alone
    assert all(math.isnan(v) for v in y[:10, n_out + 4])  # no shadow yet: a gap, not zeros
    assert not any(math.isnan(v) for v in y[10:20, n_out + 4])
    assert list(y[10:20, n_out + 1]) == [1.0] * 10
    assert candidate.steps == 20  # 10 in shadow, then active
    assert list(y[20:, n_out]) == [1.0] * 10 and list(y[20:, n_out + 1]) == [-1.0] * 10


def test_controllers_must_share_sizes_and_name_the_active_one() -> None:
    class Wide(Pi):
        n_outputs = 2

    with pytest.raises(AppError, match="share its inputs and outputs"):
        Controllers({"a": Pi(1, 1), "b": Wide(1, 1)}, "a")
    with pytest.raises(AppError, match=re.escape("active = 'c'")):
        Controllers({"a": Pi(1, 1)}, "c")
    with pytest.raises(AppError, match=r"controllers: a{24}…: a name of 5000 characters; at most 64"):
        Controllers({"a" * 5000: Pi(1, 1)}, "a" * 5000)


def _app(name: str, feed: Path | None) -> App:
    app = App(name)
    plant = app.add_task("plant", Plant(), period_ns=P, priority=81)
    ctl = app.add_task("ctl", Controllers({"fast": Pi(2.0, 5.0), "slow": Pi(0.5, 1.0)}, "fast"), period_ns=P)
    app.connect(plant.y[0], ctl.u[0])
    app.connect(ctl.y[0], plant.u[0])
    app.port("setpoint", to=ctl.u[1], initial=[1.0])
    if feed is not None:
        app.feed("ctl_switch", feed)
    return app


def test_simulate_switches_at_the_profile_cycle_and_summary_lists_it(tmp_path: Path) -> None:
    profile = tmp_path / "switch.csv"
    profile.write_text("t_s,controller,switch_at_cycle,shadow,code\n0,0,0,-1,0\n0.2,1,250,-1,0\n")
    run = rtloop.simulate(_app("sw_sim_test", profile), duration_s=0.5, out=tmp_path / "sim")
    signals = rtloop.load(tmp_path / "sim").signals
    active = np.asarray(signals["ctl.active_controller"])
    first = int(np.argmax(active == 1))
    # rows are labelled by the time their values hold from (LET: the job at 250 publishes at 251)
    assert signals.t_s[first] == pytest.approx(0.251)
    assert run.switches == [{"task": "ctl", "cycle": 250, "t_s": 0.25, "from": "fast", "to": "slow",
                             "transfer": "take_over"}]


EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "jiwy"


def _jiwy_switch_file(tmp_path: Path, name: str, cpu: int | None) -> Path:
    text = (EXAMPLES / "jiwy_switch.toml").read_text().replace('name = "jiwy_switch"', f'name = "{name}"')
    text = text.replace("cpu = 1", f"cpu = {cpu}" if cpu is not None else "")
    # jiwy_models is importable in the tests (examples/jiwy is on their path), as it is for the subprocesses
    app_file = tmp_path / f"{name}.toml"
    app_file.write_text(text)
    return app_file


def test_the_app_file_declares_controllers_and_bad_declarations_name_the_key(tmp_path: Path) -> None:
    app = load_app(_jiwy_switch_file(tmp_path, "sw_file_test", None))
    runnable = app.tasks["controller"].runnable
    assert isinstance(runnable, Controllers) and runnable.names == ("pid", "soft")
    assert runnable.alternatives[1].pan.kp == 0.15 and runnable.alternatives[0].pan.kp == 0.3
    assert app.ports["controller_switch"].signal.slice == runnable.switch_slice
    good = (tmp_path / "sw_file_test.toml").read_text()
    cases = {
        'active = "pid"': ('active = "lqr"', "tasks.controller: controllers: active = 'lqr'"),
        '[tasks.controller.controllers.soft]': ('[tasks.controller.controllers.soft]\nrunable = "x:Y"',
                                                "tasks.controller.controllers.soft.runable"),
    }
    for old, (new, expected) in cases.items():
        bad = tmp_path / "bad.toml"
        bad.write_text(good.replace(old, new))
        with pytest.raises(AppFileError, match=re.escape(expected)):
            load_app(bad)
    bad.write_text(good.replace('active = "pid"\n', ""))
    with pytest.raises(AppFileError, match=re.escape("tasks.controller.active: missing")):
        load_app(bad)


def _cli(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rtloop.cli", *args], env=env, capture_output=True, text=True,
                          timeout=120)


@pytest.mark.rt
@pytest.mark.slow
def test_a_live_switch_and_back_in_a_real_run_is_bumpless_listed_and_replays_bit_for_bit(
        tmp_path: Path, rtloop_env) -> None:
    from conftest import other_cpu, unique_name, wait_for_cycles
    from rtloop.ipc.ports import connect_app

    name = unique_name("sw_live")
    app_file = _jiwy_switch_file(tmp_path, name, other_cpu())
    run_dir = tmp_path / "run"
    process = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "run", str(app_file),  # until stopped
                                "--out", str(run_dir), "-q", "--feed",
                                f"setpoint={EXAMPLES / 'setpoints' / 'step.csv'}"],
                               env=rtloop_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        app = connect_app(name, timeout_s=60)
        wait_for_cycles(app, "controller", 600, process)  # during the step's transient
        unknown = _cli("switch", name, "controller", "lqr", env=rtloop_env)
        assert unknown.returncode == 2 and "its controllers are ['pid', 'soft']" in unknown.stderr
        assert unknown.stderr.count("\n") == 1, unknown.stderr
        shadow = _cli("switch", name, "controller", "soft", "--shadow", env=rtloop_env)
        assert shadow.returncode == 0, shadow.stderr
        assert "soft runs in shadow from cycle " in shadow.stdout, shadow.stdout
        shadow_from = int(shadow.stdout.split("from cycle ")[1].split()[0])
        wait_for_cycles(app, "controller", max(1500, shadow_from + 300), process)  # the shadow's rows before it
        # about 0.2 s ahead of the command's own start (an --at-cycle named before it started was a past
        # release when a loaded machine took over 3 s to start it): said if late, as for the switch back
        promoted = _cli("switch", name, "controller", "--promote", env=rtloop_env)
        assert promoted.returncode == 0 and "soft promoted at cycle" in promoted.stdout, promoted.stderr
        wait_for_cycles(app, "controller", int(promoted.stdout.split("at cycle ")[1].split()[0]) + 500, process)
        back = _cli("switch", name, "controller", "pid", env=rtloop_env)  # about 0.2 s ahead: said if late
        assert back.returncode == 0 and "pid active at cycle" in back.stdout, back.stderr
        # the gimbal settled long before (the step is at 0.5 s): the last rows show it stayed, without a bump
        wait_for_cycles(app, "controller", int(back.stdout.split("at cycle ")[1].split()[0]) + 500, process)
    finally:
        process.send_signal(signal.SIGTERM)  # an orderly stop, however long the machine took to get here
        _out, err = process.communicate(timeout=120)
    assert process.returncode == 0, err
    summary = json.loads((run_dir / "summary.json").read_text())
    switches = summary["switches"]
    assert [(s["from"], s["to"], s["transfer"]) for s in switches] == [
        ("pid", "soft", "take_over"), ("soft", "pid", "take_over")]
    asked = [int(line.split("at cycle ")[1].split()[0]) for line in (promoted.stdout, back.stdout)]
    for index, said in enumerate((promoted.stdout, back.stdout)):
        if "after the release named" in said:  # a machine that kept the command waiting over 0.2 s
            asked[index] = switches[index]["cycle"]
    signals = rtloop.load(run_dir).signals
    t_ns = np.round(np.asarray(signals.t_s) * 1e9).astype(np.int64)
    asked = [first_cycle_run(run_dir, "controller", cycle) for cycle in asked]  # releases it skipped, if any
    assert [s["cycle"] for s in switches] == asked  # at the release the command named
    steering = np.asarray(signals["controller.SteeringPan"])
    shadow_steering = np.asarray(signals["controller.shadow_SteeringPan"])
    active = np.asarray(signals["controller.active_controller"])

    def row(cycle: int) -> int:  # the row holding the outputs of the job of `cycle` (LET: from (cycle + 1)·P)
        return int(np.searchsorted(t_ns, (cycle + 1) * P))

    assert np.isnan(shadow_steering[: row(500)]).all()
    assert not np.isnan(shadow_steering[row(asked[0] - 200): row(asked[0])]).any()  # in shadow until promoted
    assert (active[: row(asked[0])] == 0).all() and (active[row(asked[0]): row(asked[1])] == 1).all()
    for cycle in asked:
        at = row(cycle)
        assert t_ns[at] == (cycle + 1) * P, "the switch's own cycle ran"
        changes = np.abs(np.diff(steering[at - 21: at + 21]))  # changes[20]: the new controller's first output
        normal = max(changes[:20].max(), changes[21:].max(), 1e-9)  # a cycle's change before, and after
        assert changes[20] <= 1.5 * normal, f"a bump at cycle {cycle}: {changes[20]} against {normal}"
    angle = np.asarray(signals["plant.AnglePan"])
    assert abs(angle[-1] - 0.5) < 0.01, f"the gimbal no longer follows its setpoint after the switches: {angle[-1]}"
    replayed = _cli("replay", str(run_dir), "--out", str(tmp_path / "replay"), env=rtloop_env)
    assert replayed.returncode == 0, replayed.stdout + replayed.stderr
    assert "bit for bit" in replayed.stdout
    replay_summary = json.loads((tmp_path / "replay" / "summary.json").read_text())
    assert [s["cycle"] for s in replay_summary["switches"]] == asked


RELOAD_MODULE = '''
from rtloop import Runnable


class Pi(Runnable):
    n_inputs, n_outputs = 2, 1
    output_names = ("command",)

    def __init__(self, kp, ki):
        self.kp, self.ki, self.integral = kp, ki, 0.0

    def take_over(self, u, y_last):
        self.integral = (y_last[0] - GAIN * self.kp * (u[1] - u[0])) / self.ki

    def step(self, u, y):
        error = u[1] - u[0]
        self.integral += error * self.tick.period_ns * 1e-9
        y[0] = GAIN * self.kp * error + self.ki * self.integral


GAIN = {gain}
'''

RELOAD_APP = '''
name = "{name}"
[tasks.plant]
runnable = "reload_plant:Lag"
period_ns = 1_000_000
priority = 81
{cpu}
[tasks.ctl]
period_ns = 1_000_000
priority = 80
{cpu}
active = "pi"
[tasks.ctl.controllers.pi]
runnable = "reload_ctl:Pi"
args = {{ kp = 2.0, ki = 5.0 }}
[[connect]]
from = "plant.y[0]"
to = "ctl.u[0]"
[[connect]]
from = "ctl.y[0]"
to = "plant.u[0]"
[ports.setpoint]
to = "ctl.u[1]"
initial = [1.0]
'''

PLANT_MODULE = '''
import numpy as np
from rtloop import Runnable


class Lag(Runnable):
    n_inputs, n_outputs = 1, 1

    def __init__(self):
        self.x = 0.3
        self.initial_outputs = np.array([self.x])

    def step(self, u, y):
        self.x += (u[0] - self.x) * 0.02
        y[0] = self.x
'''


def _reload_app(tmp_path: Path, name: str, cpu: int | None) -> Path:
    (tmp_path / "reload_ctl.py").write_text(RELOAD_MODULE.format(gain=1.0))
    (tmp_path / "reload_plant.py").write_text(PLANT_MODULE)
    app_file = tmp_path / f"{name}.toml"
    app_file.write_text(RELOAD_APP.format(name=name, cpu=f"cpu = {cpu}" if cpu is not None else ""))
    return app_file


def test_simulate_loads_reloaded_code_at_the_cycle_asked_and_lists_the_reload(tmp_path: Path) -> None:
    from rtloop.code_reload import code_file_name, code_id_of

    app_file = _reload_app(tmp_path, "sw_reload_sim", None)
    new_code = RELOAD_MODULE.format(gain=3.0).encode()
    code_id = code_id_of(new_code)
    out = tmp_path / "sim"
    (out / "code").mkdir(parents=True)
    (out / "code" / code_file_name("pi", code_id)).write_bytes(new_code)
    profile = tmp_path / "reload.csv"
    profile.write_text(f"t_s,controller,switch_at_cycle,shadow,code\n0,0,0,-1,0\n0.1,0,200,-1,{code_id}\n")
    app = load_app(app_file)
    app.feed("ctl_switch", profile)
    run = rtloop.simulate(app, duration_s=0.4, out=out, force=True)
    assert run.switches == [{"task": "ctl", "cycle": 200, "t_s": 0.2, "from": "pi", "to": "pi",
                             "transfer": "take_over", "code": f"{code_id:012x}"}]
    signals = rtloop.load(out).signals
    command = np.asarray(signals["ctl.command"])
    codes = np.asarray(signals["ctl.active_code"])
    t_ns = np.round(np.asarray(signals.t_s) * 1e9).astype(np.int64)
    at = int(np.searchsorted(t_ns, 201 * P))
    assert (codes[:at] == 0).all() and (codes[at:] == code_id).all()
    changes = np.abs(np.diff(command[at - 21: at + 21]))  # changes[20]: the new code's first output
    normal = max(changes[:20].max(), changes[21:].max())  # a cycle's change under the old code, and the new
    assert changes[20] <= 1.5 * normal, f"a bump at the reload: {changes[20]} against {normal}"


def test_one_file_reloaded_into_two_controllers_in_turn_loads_into_each(tmp_path: Path) -> None:
    # both controllers' classes live in one module: reloading it for the second after the first was asked
    # for the same code id, which the task took for a request it had already passed on (refused, no answer)
    from rtloop.code_reload import code_file_name, code_id_of

    app_file = _reload_app(tmp_path, "sw_reload_two", None)
    app_file.write_text(app_file.read_text().replace(
        "[[connect]]", '[tasks.ctl.controllers.pi2]\nrunnable = "reload_ctl:Pi"\nargs = { kp = 2.0, ki = 5.0 }\n'
        "[[connect]]", 1))
    new_code = RELOAD_MODULE.format(gain=3.0).encode()
    code_id = code_id_of(new_code)
    out = tmp_path / "sim"
    (out / "code").mkdir(parents=True)
    for controller in ("pi", "pi2"):
        (out / "code" / code_file_name(controller, code_id)).write_bytes(new_code)
    profile = tmp_path / "reload.csv"
    profile.write_text("t_s,controller,switch_at_cycle,shadow,code\n0,0,0,-1,0\n"
                       f"0.1,0,200,-1,{code_id}\n0.25,1,300,-1,{code_id}\n")
    app = load_app(app_file)
    app.feed("ctl_switch", profile)
    run = rtloop.simulate(app, duration_s=0.4, out=out, force=True)
    # (the second lists no code: the listing shows a code where the active code changed, and both run this one)
    assert [(s["cycle"], s["from"], s["to"]) for s in run.switches] == [(200, "pi", "pi"), (300, "pi", "pi2")]
    signals = rtloop.load(out).signals
    assert np.asarray(signals["ctl.switch_refusals"])[-1] == 0
    assert (np.asarray(signals["ctl.active_code"])[-50:] == code_id).all()
    from rtloop.report.signals import groups_of  # the report: the code id (~1e14) on an axis of its own

    groups = groups_of(signals)
    assert [g.names for g in groups if "ctl.active_code" in g.names] == [("ctl.active_code",)]
    assert any("ctl.command" in g.names for g in groups)


def test_a_module_to_reload_that_is_no_regular_file_or_too_large_is_refused_before_reading_it(tmp_path: Path) -> None:
    import os

    from rtloop.cli.reload import _read_source
    from rtloop.errors import PortValueError

    os.mkfifo(tmp_path / "fifo.py")  # opened for reading, it waited for a writer forever
    (tmp_path / "zero.py").symlink_to("/dev/zero")  # read whole, it grew until memory ran out
    (tmp_path / "folder.py").mkdir()
    for name in ("fifo.py", "zero.py", "folder.py"):
        with pytest.raises(PortValueError, match=rf"{name}: not a regular file, so not a module to load; the old code "
                                                 "keeps running"):
            _read_source(tmp_path / name)
    with (tmp_path / "huge.py").open("wb") as huge:
        huge.truncate(2 << 30)  # sparse
    with pytest.raises(PortValueError, match=r"huge.py: more than 16 MiB, not a controller's module"):
        _read_source(tmp_path / "huge.py")
    (tmp_path / "fine.py").write_text("x = 1\n")
    assert _read_source(tmp_path / "fine.py") == b"x = 1\n"


def test_reloading_the_code_the_task_was_just_asked_for_says_so_at_once(tmp_path: Path, monkeypatch) -> None:
    # the task passes a code on once: the same request again got no answer, and the command waited 10 s to
    # say "is the task running?"
    import argparse

    import rtloop.ipc.ports
    from rtloop.cli import reload
    from rtloop.code_reload import code_id_of

    module = tmp_path / "reload_ctl.py"
    module.write_text(RELOAD_MODULE.format(gain=1.0))
    code_id = code_id_of(module.read_bytes())

    class RunningApp:  # what rtloop reload reads of a running app: its switch port and its run folder
        def __init__(self) -> None:
            self.name = "sw_again"
            self.ports = {"ctl_switch": {"controllers": ["pi", "pi2"], "switch_task": "ctl", "period_ns": 1_000_000,
                                         "sources": {"pi": str(module), "pi2": str(module)}}}
            self.registry = {"summary": str(tmp_path / "run" / "summary.json")}

        def peek(self, _port: str) -> list[float]:
            return [0.0, 4200.0, -1.0, float(code_id)]  # pi asked for this code at cycle 4200

    monkeypatch.setattr(rtloop.ipc.ports, "connect_app", lambda *_args, **_kwargs: RunningApp())
    args = argparse.Namespace(app="sw_again", task="ctl", controller=None, file=None, at_cycle=None, user=None)
    with pytest.raises(rtloop.errors.PortValueError, match=r"asked for this very code for pi already "
                       r"\(code [0-9a-f]{12}, at cycle 4200\): nothing new to load; edit the file first"):
        reload.run(args)
    assert not (tmp_path / "run").exists()  # nothing kept, nothing written to the task


@pytest.mark.rt
@pytest.mark.slow
def test_live_reload_acts_from_the_named_release_refuses_bad_code_and_replays(tmp_path: Path, rtloop_env) -> None:
    from conftest import other_cpu, unique_name, wait_for_cycles
    from rtloop.ipc.ports import connect_app

    name = unique_name("sw_reload")
    app_file = _reload_app(tmp_path, name, other_cpu())
    run_dir = tmp_path / "run"
    module = tmp_path / "reload_ctl.py"
    process = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "run", str(app_file),  # until stopped
                                "--out", str(run_dir), "-q"],
                               env=rtloop_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        app = connect_app(name, timeout_s=60)
        wait_for_cycles(app, "ctl", 500, process)
        module.write_text(RELOAD_MODULE.format(gain=1.0).replace("def step(self, u, y):", "def step(self, u, y)"))
        broken = _cli("reload", name, "ctl", env=rtloop_env)
        assert broken.returncode == 2 and "expected ':'" in broken.stderr and "old code keeps running" in \
            broken.stderr, broken.stderr
        module.write_text(RELOAD_MODULE.format(gain="float('nan')"))
        nan = _cli("reload", name, "ctl", env=rtloop_env)
        assert nan.returncode == 2 and "not finite" in nan.stderr, nan.stderr
        module.write_text(RELOAD_MODULE.format(gain=3.0))
        good = _cli("reload", name, "ctl", env=rtloop_env)
        assert good.returncode == 0 and "pi reloaded from" in good.stdout and "prepared in" in good.stdout, good.stderr
        wait_for_cycles(app, "ctl", int(good.stdout.split("at cycle ")[1].split()[0]) + 500, process)
    finally:
        process.send_signal(signal.SIGTERM)  # an orderly stop, however long the machine took to get here
        _out, err = process.communicate(timeout=120)
    assert process.returncode == 0, err
    asked = int(good.stdout.split("at cycle ")[1].split()[0])
    summary = json.loads((run_dir / "summary.json").read_text())
    reloads = summary["switches"]
    assert [(s["cycle"], s["to"], s["transfer"]) for s in reloads] == [(asked, "pi", "take_over")]
    kept = sorted(p.name for p in (run_dir / "code").glob("*.py"))
    # the code it started with, the NaN one (refused in the task) and the good one; a syntax error never left the CLI
    assert len(kept) == 3 and json.loads((run_dir / "code" / "start.json").read_text())["ctl"]["pi"]
    assert len(list((run_dir / "code").glob("*.code"))) == 2  # compiled by the command, not in the task
    replayed = _cli("replay", str(run_dir), "--out", str(tmp_path / "replay"), env=rtloop_env)
    assert replayed.returncode == 0 and "bit for bit" in replayed.stdout, replayed.stdout + replayed.stderr


def test_the_jiwy_switch_example_switches_mid_transient_without_a_bump_and_still_follows(tmp_path: Path) -> None:
    app = load_app(EXAMPLES / "jiwy_switch.toml")
    app.feed("setpoint", EXAMPLES / "setpoints" / "step.csv")
    app.feed("controller_switch", EXAMPLES / "setpoints" / "switches.csv")
    run = rtloop.simulate(app, duration_s=3, out=tmp_path / "sim")
    assert [(s["cycle"], s["from"], s["to"]) for s in run.switches] == [(560, "pid", "soft"), (1500, "soft", "pid")]
    signals = rtloop.load(tmp_path / "sim").signals
    steering = np.asarray(signals["controller.SteeringPan"])
    t_ns = np.round(np.asarray(signals.t_s) * 1e9).astype(np.int64)
    for cycle in (560, 1500):
        at = int(np.searchsorted(t_ns, (cycle + 1) * P))
        changes = np.abs(np.diff(steering[at - 21: at + 21]))
        assert changes[20] <= 1.5 * max(changes[:20].max(), changes[21:].max()), f"a bump at cycle {cycle}"
    for axis, setpoint in (("plant.AnglePan", 0.5), ("plant.AngleTilt", 0.3)):
        assert abs(signals[axis][-1] - setpoint) < 0.01, f"{axis} no longer follows its setpoint"


def first_cycle_run(run_dir: Path, task: str, cycle: int) -> int:
    """The first cycle from ``cycle`` on that ``task`` ran (timing.csv): a switch asked for a release
    the task skipped (an overrun under load) acts at the next one it runs."""
    return next(c for c in ran_cycles(run_dir, task) if c >= cycle)


EXAMPLE_DCMOTOR_PROFILE = Path(__file__).resolve().parents[1] / "examples" / "dcmotor" / "profiles" / "speed_steps.csv"


LATE_FIRST_STEP_MODULE = '''
import time

from serial_motor import PiSpeed


class LateFirstPi(PiSpeed):
    """The hot PI, whose first step ends {late_ms} ms late: the overrun a loaded machine may put on a switch."""

    late = True

    def step(self, u, y):
        super().step(u, y)
        if self.late:
            self.late = False
            time.sleep({late_ms} / 1000)
'''


def ran_cycles(run_dir: Path, task: str) -> list[int]:
    """The cycles ``task`` ran (timing.csv), in order: the releases at which its devices were written."""
    with open(run_dir / "timing.csv") as file:
        return sorted(int(row["cycle"]) for row in csv.DictReader(file) if row["task"] == task)


@pytest.mark.rt
@pytest.mark.slow
def test_a_device_app_switched_live_keeps_its_commands_within_their_rate_limits(tmp_path: Path, rtloop_env) -> None:
    """The DC motor over a pty: its PI switched live to a hotter one with no take_over and no blend (a plain
    switch: the new integrator starts from 0, so the voltage asked for jumps); what the driver is sent
    still moves at most by its rate limit (1 V/ms here), and the cycles it held the command back are counted.

    The switch's own cycle overruns by 5 ms (the hot PI's first step sleeps), as a loaded machine made it do
    once: the task skips the releases it missed, so the first command computed by the new controller is
    written at the first release it runs after the switch, not at the one after it. A device is written at
    the releases a task runs only (signals.csv's row of a skipped release shows the command the device still
    holds), so the rule is: each value sent moves from the last one sent by at most rate_per_s times the
    time between them (the guard allows one step per write, whatever the time since)."""
    from conftest import wait_for_app, wait_for_cycles
    from rtloop.ipc.switch_requests import switch
    from test_dcmotor_serial import Driver, example_file

    driver = Driver(tmp_path)
    period_ns = 2_000_000  # example_file's period
    try:
        app_file = example_file(tmp_path, driver.link, "sw_dcm", period_ns=period_ns)
        (tmp_path / "late_pi.py").write_text(LATE_FIRST_STEP_MODULE.format(late_ms=5.0))
        text = app_file.read_text()
        head, rest = text.split("[tasks.pi]\n", 1)
        _pi, devices = rest.split("[devices.motor]", 1)
        text = head + f"""[tasks.pi]
period_ns = {period_ns}
priority = 80
active = "gentle"
blend_s = 0
[tasks.pi.controllers.gentle]
runnable = "serial_motor:PiSpeed"
parameters = {{ kp = 0.05, ki = 3.0 }}
[tasks.pi.controllers.hot]
runnable = "late_pi:LateFirstPi"
parameters = {{ kp = 2.0, ki = 3.0 }}

[devices.motor]""" + devices.replace("rate_per_s = 12_000.0", "rate_per_s = 1_000.0")  # 2 V a period
        profile = tmp_path / "hold_150.csv"  # 150 rad/s from 0.1 s on: the PI's integrator holds the voltage
        profile.write_text("t_s,setpoint_rad_s\n0,0\n0.1,150\n")
        text = text.replace(str(EXAMPLE_DCMOTOR_PROFILE), str(profile))
        assert "controllers.hot" in text
        app_file.write_text(text)
        name = text.split('name = "')[1].split('"')[0]
        run_dir = tmp_path / "run"
        process = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--out", str(run_dir),
                                    "-q"], env=rtloop_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            app = wait_for_app(name, process)
            done = wait_for_cycles(app, "pi", 300, process)
            # from this process (what rtloop switch calls): a CLI's start took over 5 s on a loaded machine
            [answer] = switch(app, {"pi": "hot"}, at_cycle=done + 750)  # 1.5 s ahead
            wait_for_cycles(app, "pi", answer.at_cycle + 100, process)
        finally:
            process.send_signal(signal.SIGTERM)
            _out, err = process.communicate(timeout=120)
    finally:
        driver.stop()
    assert process.returncode == 0, err
    summary = json.loads((run_dir / "summary.json").read_text())
    signals = rtloop.load(run_dir).signals
    sent = np.asarray(signals["motor.voltage_V"])
    asked_for = np.asarray(signals["pi.voltage_V"])
    t_ns = np.round(np.asarray(signals.t_s) * 1e9).astype(np.int64)
    ran = ran_cycles(run_dir, "pi")
    asked = next(c for c in ran if c >= answer.at_cycle)  # releases the loaded machine made the task skip
    assert [(s["cycle"], s["to"], s["transfer"]) for s in summary["switches"]] == [(asked, "hot", "direct")]
    written = next(c for c in ran if c > asked)  # the first release run after the switch: its command is written
    assert written >= asked + 3, f"the switch's cycle did not overrun 5 ms: the next release run is {written}"
    rows = np.searchsorted(t_ns, np.array(ran) * period_ns)  # the rows of the releases the task ran
    assert (t_ns[rows] == np.array(ran) * period_ns).all()
    kept = ~np.isnan(sent[rows])  # (a row the recording lost is an empty cell: no value to compare)
    sent_t_ns, sent_v = t_ns[rows][kept], sent[rows][kept]
    limit_v_per_s = 1_000.0
    moved = np.abs(np.diff(sent_v))
    allowed = limit_v_per_s * np.diff(sent_t_ns) / 1e9
    assert (moved <= allowed + 1e-9).all(), "a command moved faster than its rate limit since the last one sent"
    assert moved.max() <= limit_v_per_s * period_ns / 1e9 + 1e-9, "more than one period's step in one write"
    switched_row, written_row = (int(np.searchsorted(t_ns, c * period_ns)) for c in (asked + 1, written))
    assert abs(asked_for[switched_row] - asked_for[switched_row - 1]) > 4.0, "the switch did not jump: nothing shown"
    assert (sent[switched_row:written_row] == sent[switched_row - 1]).all(), "a command shown before it was written"
    assert abs(sent[written_row] - sent[switched_row - 1]) == pytest.approx(2.0), \
        "the rate limit did not hold the jump back at the first write after the switch"
    assert summary["devices"]["motor"]["rate_limited_cycles"].get("voltage_V", 0) >= 1


class _FakeApp:
    """The parts of a RunningApp that switch requests use: two tasks of controllers, T0 an hour ago."""

    name = "fake"

    def __init__(self) -> None:
        import time

        self.t0_ns = time.clock_gettime_ns(time.CLOCK_MONOTONIC) - 3600 * 10**9
        self.ports = {f"{task}_switch": {"controllers": ["pid", "lqr"], "switch_task": task, "period_ns": period}
                      for task, period in (("left", 1_000_000), ("right", 2_000_000))}
        self.written: list[tuple[str, list[float]]] = []

    def epoch_ns(self) -> int:
        return self.t0_ns

    def peek(self, port: str) -> np.ndarray:
        return np.array([0.0, 0.0, -1.0, 0.0])

    def write(self, port: str, values: list[float]) -> None:
        self.written.append((port, values))


def test_each_switch_answer_names_its_release_in_plain_words() -> None:
    from rtloop.ipc.switch_requests import SwitchPort, _request

    port = SwitchPort("controller", "controller_switch", ("pid", "soft"), 1_000_000)
    current = [0.0, 0.0, -1.0, 0.0]  # pid active, no shadow
    said = {mode: _request(current, port, "soft", 6605, mode)[1] for mode in ("active", "shadow")}
    assert said["active"] == "soft active at cycle 6605 (t = 6.605000 s)"
    assert said["shadow"] == "soft runs in shadow from cycle 6605 (t = 6.605000 s)"  # was "from at cycle"
    values, promoted = _request([0.0, 0.0, 1.0, 0.0], port, None, 7000, "promote")
    assert promoted == "soft promoted at cycle 7000 (t = 7.000000 s)" and values[:3] == [1.0, 7000.0, 1.0]


def test_a_shadow_of_the_active_controller_or_a_stop_of_no_shadow_is_refused_not_reported_done() -> None:
    from rtloop.errors import PortValueError
    from rtloop.ipc.switch_requests import SwitchPort, _request

    port = SwitchPort("controller", "controller_switch", ("pid", "soft"), 1_000_000)
    with pytest.raises(PortValueError, match="pid is the active controller of task 'controller'"):
        _request([0.0, 0.0, -1.0, 0.0], port, "pid", 100, "shadow")  # the task would ignore it
    with pytest.raises(PortValueError, match="task 'controller' runs no shadow controller to stop"):
        _request([0.0, 0.0, -1.0, 0.0], port, None, 100, "stop_shadow")
    assert _request([0.0, 0.0, 1.0, 0.0], port, None, 100, "stop_shadow")[0][2] == -1.0


def test_an_at_cycle_past_what_the_switch_port_holds_names_the_option() -> None:
    from rtloop.errors import PortValueError
    from rtloop.ipc.switch_requests import switch

    app = _FakeApp()
    with pytest.raises(PortValueError, match=r"at cycle 100000000000000000000000000000: task 'left' would reach it "
                                             r"at its cycle 100000000000000000000000000000, past the last a switch"):
        switch(app, {"left": "lqr"}, at_cycle=10**29)  # type: ignore[arg-type]
    assert app.written == []


def test_a_reload_at_a_cycle_past_what_the_switch_port_holds_names_the_option(tmp_path: Path,
                                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """rtloop reload --at-cycle 1e29 said 'port left_switch (...): value 1e+29 at index 1 is outside its range'."""
    import argparse

    import rtloop.ipc.ports as ports
    from rtloop.cli import reload
    from rtloop.errors import PortValueError

    app = _FakeApp()
    app.registry = {"summary": str(tmp_path / "summary.json")}  # type: ignore[attr-defined]
    monkeypatch.setattr(ports, "connect_app", lambda *_, **__: app)
    module = tmp_path / "ctl.py"
    module.write_text("X = 1\n")
    def write(port: str, values: list[float]) -> None:  # the real port refuses it; the command then waited
        pytest.fail(f"requested: {port} {values}")

    app.write = write  # type: ignore[method-assign]
    with pytest.raises(PortValueError, match=r"at cycle 100000000000000000000000000000: task 'left' would reach it"):
        reload.run(argparse.Namespace(app="fake", task="left", controller="lqr", file=module, at_cycle=10**29,
                                      user=None))


def test_several_tasks_switch_at_one_instant_or_none_does() -> None:
    from rtloop.errors import PortValueError
    from rtloop.ipc.switch_requests import switch

    app = _FakeApp()
    with pytest.raises(PortValueError, match="task 'right' has no controller 'mpc'"):
        switch(app, {"left": "lqr", "right": "mpc"})  # type: ignore[arg-type]
    assert app.written == []  # the left task was not switched alone
    answers = switch(app, {"left": "lqr", "right": "lqr"}, at_cycle=3_700_000)  # type: ignore[arg-type]
    assert [(a.task, a.at_cycle) for a in answers] == [("left", 3_700_000), ("right", 1_850_000)]  # one instant
    assert app.written == [("left_switch", [1.0, 3_700_000.0, -1.0, 0.0]),
                           ("right_switch", [1.0, 1_850_000.0, -1.0, 0.0])]
    with pytest.raises(PortValueError, match="is at cycle"):
        switch(app, {"left": "pid"}, at_cycle=10)  # type: ignore[arg-type]


RELOAD_THREAD_POLICY = '''
import os, sys, time
from pathlib import Path
from rtloop.code_reload import CodeReloader
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))  # as a task's loop runs
except PermissionError:
    print("no SCHED_FIFO"); sys.exit(0)
reloader = CodeReloader(None, Path(sys.argv[1]), [], wait=False)
deadline = time.monotonic() + 10
while os.sched_getscheduler(reloader.thread.native_id) == os.SCHED_FIFO and \\
        os.sched_getparam(reloader.thread.native_id).sched_priority == 80 and time.monotonic() < deadline:
    time.sleep(0.01)  # until the thread has set its own
print(os.sched_getscheduler(reloader.thread.native_id) == os.SCHED_FIFO,
      os.sched_getparam(reloader.thread.native_id).sched_priority)
reloader.close()
'''


def test_the_reload_thread_of_a_real_time_task_runs_at_fifo_1_below_the_loop_above_any_busy_process(
        tmp_path: Path) -> None:
    """Under SCHED_OTHER the reload thread, preempted by any busy process while it held the interpreter's
    lock, kept the waking loop waiting as long: 108 ms and 28 misses at 1 kHz while a reload was prepared
    on a loaded machine (benchmarks/bench_switch.py)."""
    found = subprocess.run([sys.executable, "-c", RELOAD_THREAD_POLICY, str(tmp_path)], capture_output=True,
                           text=True, timeout=60)
    assert found.returncode == 0, found.stderr
    if found.stdout.strip() == "no SCHED_FIFO":
        pytest.skip("SCHED_FIFO is not permitted here (not root, no CAP_SYS_NICE, no RLIMIT_RTPRIO)")
    assert found.stdout.split() == ["True", "1"]


def test_the_reload_thread_loads_the_code_rtloop_reload_compiled_and_compiles_nothing_itself(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A module's compilation is one C call that holds the interpreter's lock (9 ms for jiwy_models.py on
    this machine): in the task's reload thread, a loop waking meanwhile waited as long (misses while a
    reload was prepared, benchmarks/bench_switch.py). The command compiles it; the thread loads that."""
    import copy
    import importlib

    from rtloop import code_reload
    from rtloop.code_reload import CodeReloader, code_file_name, code_id_of, compiled_code, compiled_file_name

    (tmp_path / "reload_compiled_ctl.py").write_text(RELOAD_MODULE.format(gain=1.0))
    monkeypatch.syspath_prepend(str(tmp_path))
    module = importlib.import_module("reload_compiled_ctl")
    controllers = Controllers({"pi": module.Pi(kp=2.0, ki=5.0)}, "pi")
    code_dir = tmp_path / "code"
    code_dir.mkdir()
    new = RELOAD_MODULE.format(gain=3.0).encode()
    code_id = code_id_of(new)
    kept = code_dir / code_file_name("pi", code_id)
    kept.write_bytes(new)
    compiled_here: list[str] = []

    def compile_spy(source: Any, filename: str, *rest: Any, **named: Any) -> Any:
        compiled_here.append(filename)
        return compile(source, filename, *rest, **named)

    reloader = CodeReloader(controllers, code_dir, [copy.deepcopy(controllers.alternatives[0])], wait=True)
    try:
        monkeypatch.setattr(code_reload, "compile", compile_spy, raising=False)
        assert reloader.build_now(0, code_id).kp == 2.0  # no compiled copy (a profile's reload in simulate)
        assert compiled_here == [str(kept)]
        (code_dir / compiled_file_name("pi", code_id)).write_bytes(compiled_code(new, kept, code_id))
        compiled_here.clear()
        built = reloader.build_now(0, code_id)
        assert compiled_here == [], "the reload thread compiled the module though the command had"
        built.bind_inputs(np.zeros(2))
        built.tick = TickInfo(cycle=0, period_ns=P)
        y = np.zeros(1)
        built.step(np.array([0.0, 1.0]), y)
        assert y[0] == pytest.approx(3.0 * 2.0 + 5.0 * 1e-3)  # the new code (GAIN = 3) acts
        other = compiled_code(RELOAD_MODULE.format(gain=5.0).encode(), kept, code_id + 1)  # not this code's
        (code_dir / compiled_file_name("pi", code_id)).write_bytes(other)
        compiled_here.clear()
        reloader.build_now(0, code_id)
        assert compiled_here == [str(kept)], "a compiled copy of other code was used"
    finally:
        reloader.close()
