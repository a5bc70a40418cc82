"""``rtloop report A B`` of runs carrying live port writes: a simulation and a run, a run and its replay.

Issue 30, defect 1: the overlay crashed (IndexError in ``_mark_inputs``) as soon as a run after the
first carried a live write. Here a "run" is a simulation with port writes (its inputs.csv says what
entered, as a run's does), its replay replays them, and a plain simulation has none.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from matplotlib.lines import Line2D

import rtloop
from replay_helpers import pi_loop_app
from rtloop.cli.main import main as cli_main
from rtloop.record.load import load
from rtloop.report import signals as signal_figures

WRITES = {("controller", 30): [("setpoint", [1.0, -1.0])], ("controller", 120): [("setpoint", [0.5, 0.25])]}


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    from rtloop.runtime.replay import replay

    base = tmp_path_factory.mktemp("overlay")
    rtloop.simulate(pi_loop_app("overlay_sim"), 0.2, base / "sim")
    rtloop.simulate(pi_loop_app("overlay_rt"), 0.2, base / "rt", port_writes=WRITES)
    (base / "rt" / "inputs.csv").write_text("task,cycle,port,values\ncontroller,30,setpoint,1.0 -1.0\n"
                                            "controller,120,setpoint,0.5 0.25\n")
    result = replay(base / "rt", base / "rt-replay", app=pi_loop_app("overlay_rt"))
    assert result.equal and result.port_inputs == 2
    assert set(load(base / "rt-replay").inputs) == {"setpoint"}, "the replay carries the run's writes"
    return {"sim": base / "sim", "rt": base / "rt", "replay": base / "rt-replay"}


@pytest.mark.parametrize("pair", [("sim", "rt"), ("rt", "replay")])
def test_the_overlay_of_runs_with_live_writes_is_drawn(runs: dict[str, Path], pair: tuple[str, str],
                                                      tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "report"
    assert cli_main(["report", str(runs[pair[0]]), str(runs[pair[1]]), "--out", str(out)]) == 0, capsys.readouterr()
    assert (out / "report-figures" / "compare-signals.png").is_file()
    assert "internal error" not in capsys.readouterr().err


def test_each_runs_writes_are_marked_in_its_colour_and_labelled_once(runs: dict[str, Path]) -> None:
    """Sim vs run: the run's two writes are marked (lines in its colour) and labelled; run vs replay:
    both carry the same two writes, drawn in both colours, labelled once."""
    def overlay(*names: str) -> tuple[dict[str, int], list[str]]:
        loaded = [(name, load(runs[name])) for name in names]
        fig = signal_figures.comparison_figure([(n, r.signals, r.inputs) for n, r in loaded])
        assert fig is not None
        signal_axes = fig.get_axes()[::2]
        lines: dict[str, int] = {}
        for line in signal_axes[0].get_lines():
            if isinstance(line, Line2D) and list(line.get_xdata()) in ([0.03, 0.03], [0.12, 0.12]):
                lines[str(line.get_color())] = lines.get(str(line.get_color()), 0) + 1
        labels = [t.get_text() for t in signal_axes[0].texts]
        return lines, labels

    lines, labels = overlay("sim", "rt")
    assert lines == {signal_figures.RUN_COLORS[1]: 2}
    assert labels == ["setpoint ← 1, -1", "setpoint ← 0.5, 0.25"]
    lines, labels = overlay("rt", "replay")
    assert lines == {signal_figures.RUN_COLORS[0]: 2, signal_figures.RUN_COLORS[1]: 2}
    assert labels == ["setpoint ← 1, -1", "setpoint ← 0.5, 0.25"]
