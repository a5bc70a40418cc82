"""Reading a run's logs for its replay: the summary, the app it ran, timing.csv, inputs.csv, what a
device read, and what the run says it lost on the way. Everything here reads files and checks them;
nothing simulates."""

from __future__ import annotations

import csv
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.app.builder import App
from rtloop.app.sources import changes_since
from rtloop.errors import AppError
from rtloop.record.csvfiles import column_names, read_inputs_csv
from rtloop.record.jsonfile import parse_json
from rtloop.runtime.session import UNFINISHED_FOLDER
from rtloop.runtime.simulate import PortWrites
from rtloop.seconds import ns_from_seconds
from rtloop.text import counted


@dataclass(frozen=True)
class CycleRecord:
    """One cycle of a task as the run's ``timing.csv`` holds it (times in ns since T0)."""

    cycle: int
    release_ns: int
    start_ns: int
    end_ns: int


def read_summary(run_dir: Path) -> dict[str, Any]:
    path = run_dir / "summary.json"
    if not path.is_file():
        raise AppError(f"{run_dir}: no summary.json; is it the output folder of `rtloop run`?")
    try:
        summary: dict[str, Any] = parse_json(path.read_text())
        return summary
    except ValueError as error:
        raise AppError(f"{path}: not JSON ({error})") from None


def load_replay_app(run_dir: Path) -> tuple[App, float | None]:
    """The app of a run (from replay.json), with its feeds, and the run's ``--duration`` (None: none)."""
    from rtloop.app.appfile import load_app

    info_path = run_dir / "replay.json"
    if not info_path.is_file():
        raise AppError(f"{run_dir}: no replay.json; is it the output folder of `rtloop run`?")
    try:
        info = parse_json(info_path.read_text())
    except (OSError, ValueError) as error:
        raise AppError(f"{info_path}: not readable JSON ({error})") from None
    if not isinstance(info, dict):
        raise AppError(f"{info_path}: not a replay.json (expected a JSON object)")
    if info.get("source", "<python>") == "<python>":
        raise AppError(f"{run_dir}: the app was built in Python; call rtloop.runtime.replay.replay(run_dir, out, app)")
    app = load_app(info["source"])
    for port, feed in info.get("feeds", {}).items():
        app.feed(port, feed)
    duration_s = info.get("duration_s")
    return app, None if duration_s is None else float(duration_s)


def play_back_devices(app: App, run_dir: Path) -> None:
    """Put in each device's place what it read in the run: the task inputs it fed, as recorded
    (a device's readings are always recorded, in the row of the release that read them)."""
    from rtloop.io.twin import PlaybackTwin

    with open(run_dir / "signals.csv", newline="") as file:
        rows = list(csv.reader(file))
    header = {name: index for index, name in enumerate(rows[0])} if rows else {}
    for spec in app.devices.values():
        device, owner = spec.device, app.tasks[spec.task]
        period_ns = owner.config.period_ns
        readings: dict[int, np.ndarray] = {}
        for link in app.device_links:
            if link.source.task != spec.name:
                continue
            names = column_names(link.target, owner.runnable.input_names, owner.runnable.output_names)
            missing = [name for name in names if name not in header]
            if missing:
                raise AppError(f"{run_dir}: signals.csv has no column {missing[0]} (what device {spec.name!r} "
                               "read): a run of an older rtloop; it cannot be replayed without the device")
            columns = [header[name] for name in names]
            for row in rows[1:]:
                t_ns = ns_from_seconds(row[0])
                cycle = t_ns // period_ns  # inputs are recorded at the release that read them (outputs at t + P)
                if cycle < 0 or t_ns % period_ns or any(row[c] == "" for c in columns):
                    continue
                values = readings.setdefault(cycle, np.zeros(device.n_outputs))
                values[link.source.slice] = [float(row[c]) for c in columns]
        spec.twin = PlaybackTwin(spec.name, device.n_inputs, device.n_outputs, readings)


def port_writes(run_dir: Path) -> PortWrites:
    path = run_dir / "inputs.csv"
    writes: PortWrites = {}
    if not path.exists():
        return writes
    try:
        rows = read_inputs_csv(path)
    except ValueError as error:
        raise AppError(str(error)) from None
    for task, cycle, port, values in rows:
        writes.setdefault((task, cycle), []).append((port, values))
    return writes


def whole_lines(file: Iterable[str], name: str, cut: list[str]) -> Iterator[str]:
    """The lines of a file the recorder wrote, without a last line cut short (a full disk or a
    kill -9 stopped the writer in the middle of it): where it was cut is added to ``cut``."""
    for number, line in enumerate(file, start=1):
        if not line.endswith("\n"):
            cut.append(f"{name} line {number}: its last line is cut short (the recording stopped there); left out")
            return
        yield line


def unfinished(run_dir: Path, summary: dict[str, Any] | None = None) -> str:
    """Why a run's files were never joined (a run killed, or still running), '' if they were
    (``summary``: its summary.json, when it has one)."""
    if (run_dir / UNFINISHED_FOLDER).is_dir():
        return (f"{run_dir}: the run never finished (killed, or still running): its recording is in "
                f"{UNFINISHED_FOLDER}/, never joined into timing.csv and signals.csv, so it cannot be replayed "
                "(rtloop.load reads it)")
    if summary is not None and summary.get("running"):
        return (f"{run_dir}: the run never finished (summary.json still says running: killed, or still "
                "running): its timing.csv is not whole, so it cannot be replayed")
    return ""


def read_timing(run_dir: Path, periods_ns: dict[str, int],
                cut: list[str] | None = None) -> tuple[dict[str, list[CycleRecord]], int]:
    """Each task's cycles from timing.csv (times since T0), in order, and T0 (ns, the run's clock).

    A last line cut short is left out, and said in ``cut``."""
    path = run_dir / "timing.csv"
    if not path.is_file():
        raise AppError(f"{run_dir}: no timing.csv: the run's timeline is unknown")
    cycles: dict[str, list[CycleRecord]] = {name: [] for name in periods_ns}
    t0_ns: int | None = None
    with open(path, newline="") as file:
        for number, row in enumerate(csv.DictReader(whole_lines(file, path.name, [] if cut is None else cut)),
                                     start=2):
            try:
                task, cycle = row["task"], int(row["cycle"])
                release, start, end = int(row["release_ns"]), int(row["start_ns"]), int(row["end_ns"])
                period = periods_ns[task]
            except (KeyError, TypeError, ValueError):
                raise AppError(f"{path}:{number}: expected task,cycle,release_ns,start_ns,end_ns of a task "
                               f"of the app ({', '.join(periods_ns)})") from None
            t0_ns = release - cycle * period if t0_ns is None else t0_ns
            if release - cycle * period != t0_ns:
                raise AppError(f"{path}:{number}: release {release} of {task} cycle {cycle} is off its timeline")
            cycles[task].append(CycleRecord(cycle, release - t0_ns, start - t0_ns, end - t0_ns))
    for records in cycles.values():
        records.sort(key=lambda record: record.cycle)
    return cycles, t0_ns or 0


def changed_files(run_dir: Path) -> list[str]:
    """The files of the run's app (replay.json's ``files``) whose content is not what the run loaded."""
    try:
        recorded = parse_json((run_dir / "replay.json").read_text()).get("files") or {}
    except (OSError, ValueError, AttributeError):
        return []  # no replay.json, or one from before files were recorded: the loading says what is wrong
    return changes_since({str(path): str(digest) for path, digest in recorded.items()}) if isinstance(
        recorded, dict) else []


def stale_device_note(name: str, device: dict[str, Any]) -> str:
    """The replay's log line for a device that read stale values in the run (summary.json ``devices``)."""
    count, cycles = int(device.get("stale_cycles") or 0), list(device.get("first_stale_cycles") or [])
    shown = ", ".join(str(cycle) for cycle in cycles[:10]) + (", …" if count > 10 else "")
    lag = int(device.get("longest_lag_cycles") or 0)
    return (f"device {name!r} read stale values in {counted(count, 'cycle')} ({shown}; the longest lag "
            f"{counted(lag, 'cycle')} in a row): played back as the run read them")


def recording_losses(recording: dict[str, Any], run_dir: Path) -> dict[str, dict[str, int]]:
    """summary.json's ``recording.lost`` (per kind, per task, counts > 0): {} where it says nothing."""
    lost = recording.get("lost") or {}
    try:
        return {str(kind): {str(task): int(count) for task, count in counts.items() if int(count) > 0}
                for kind, counts in lost.items()}
    except (AttributeError, TypeError, ValueError):
        raise AppError(f"{run_dir / 'summary.json'}: recording.lost is not counts per kind and task") from None


def run_end_ns(summary: dict[str, Any], records: dict[str, list[CycleRecord]], periods_ns: dict[str, int]) -> int:
    """When the run's releases ended (since T0): its duration if it ran to it, else its tasks' last records."""
    last = max((run[-1].release_ns + periods_ns[name] for name, run in records.items() if run), default=0)
    duration_s = summary.get("duration_s")
    if summary.get("stopped_by") == "duration" and isinstance(duration_s, int | float) and duration_s > 0:
        return max(last, round(duration_s * 1e9))
    return last


def lost_on_the_way(recording: dict[str, Any], run_dir: Path, recorded_until_ns: int | None = None) -> list[str]:
    """What the run's summary says it lost (besides timing records: those cut the timeline) and the
    replay therefore cannot check, each with what it means for the replay."""
    losses = recording_losses(recording, run_dir)
    lost = []
    for task, count in losses.get("inputs", {}).items():
        lost.append(f"the run took {count} values from ports of {task} that it did not log (recording.lost.inputs: "
                    "its input log was full): the replay cannot feed them, and the run does not say when they "
                    "came, so rows may differ from then on")
    for task, count in (recording.get("reads_dropped") or {}).items():
        lost.append(f"the run's read log of {task} dropped {count} stale connection reads "
                    "(recording.reads_dropped: ring full): the replay reads what logical execution time promised "
                    "there instead")
    if recording.get("stopped"):
        until = f" (timing.csv holds every task up to t = {recorded_until_ns / 1e9!r} s)" if recorded_until_ns else ""
        lost.append(f"the recording stopped during the run ({recording['stopped']}): its files end there{until}, "
                    "what was recorded is replayed and compared, the rest of the run is not")
    return lost
