"""F-inputs-unbounded: inputs.csv (a row per value taken from a live port) rotates with the
``--keep`` flight window like timing.csv and reads.csv, so a run of weeks fed by a 1-kHz topic
keeps a bounded file; the window's replay needs only the inputs from its start on (the task
snapshots hold the values taken before)."""

from __future__ import annotations

import csv
from pathlib import Path

import rtloop
from conftest import unique_name
from rt_test_runnables import Integrator
from rtloop import App
from rtloop.record.flight import SEGMENTS_DIR

P = 1_000_000
CYCLES = 20_000  # 20 s at 1 kHz; --keep 1: segments of 1 s, a few of them kept at the end
EVERY = 50  # a value written every 50 ms


def _app(name: str) -> App:
    app = App(name)
    plant = app.add_task("plant", Integrator(1), period_ns=P, policy="other")
    app.port("load", to=plant.u)
    app.record(plant.y, plant.u)
    return app


def _writes() -> dict[tuple[str, int], list[tuple[str, list[float]]]]:
    return {("plant", cycle): [("load", [cycle / 1000.0])] for cycle in range(EVERY, CYCLES, EVERY)}


def _input_cycles(run: Path) -> list[int]:
    with open(run / "inputs.csv", newline="") as file:
        return [int(row["cycle"]) for row in csv.DictReader(file)]


def test_inputs_csv_holds_the_window_not_the_whole_run(tmp_path: Path) -> None:
    name = unique_name("inputs_win")
    rtloop.simulate(_app(name), CYCLES / 1000, tmp_path / "all", port_writes=_writes())
    assert _input_cycles(tmp_path / "all") == list(range(EVERY, CYCLES, EVERY))  # without --keep: every one

    rtloop.simulate(_app(name), CYCLES / 1000, tmp_path / "kept", port_writes=_writes(), keep_s=1.0)
    kept = _input_cycles(tmp_path / "kept")
    assert not (tmp_path / "kept" / SEGMENTS_DIR).exists()  # joined at the end
    assert kept == list(range(kept[0], CYCLES, EVERY)), kept  # the newest, without a hole
    assert CYCLES - kept[0] <= 6_000, f"inputs.csv starts at cycle {kept[0]}: not bounded by the window"
    # the window's replay from its snapshot (a real run's): tests/test_replay.py, _keep_run_replays_its_window


def test_a_run_killed_during_keep_is_loaded_with_the_inputs_of_its_segments(tmp_path: Path) -> None:
    """rtloop.load reads inputs.csv's segments as it does the other files' (a run killed before the join)."""
    name = unique_name("inputs_seg")
    out = tmp_path / "kept"
    rtloop.simulate(_app(name), 3.0, out, port_writes=_writes(), keep_s=1.0)
    joined = rtloop.load(out).inputs["load"].values[:, 0].tolist()
    segments = out / SEGMENTS_DIR
    segments.mkdir()
    lines = (out / "inputs.csv").read_text().splitlines(keepends=True)
    half = len(lines) // 2
    (segments / "000000-inputs.csv").write_text("".join(lines[:half]))
    (segments / "000001-inputs.csv").write_text(lines[0] + "".join(lines[half:]))
    (out / "inputs.csv").unlink()
    run = rtloop.load(out)
    assert run.inputs["load"].values[:, 0].tolist() == joined
    assert any("inputs.csv: read from 2 flight-recorder segment(s)" in p for p in run.problems), run.problems
