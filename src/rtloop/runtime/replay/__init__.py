"""Replay: re-simulate a whole run offline, its timing faults included, and compare it bit for bit.

A run leaves what its tasks really did beside its signals: ``timing.csv`` (every cycle
run, so the releases skipped after an overrun show as gaps), ``reads.csv`` (every read of
a connection that got an older sample than logical execution time promised: a stale
read), ``inputs.csv`` (every value taken from a live port, with the cycle that took it)
and ``replay.json`` (the app file and profile feeds). :func:`replay` rebuilds the app and
simulates it along that real timeline (:class:`RunTimeline`): each task runs the cycles
it ran, skips the ones it skipped, and reads the samples it read. Then the replay's
``signals.csv`` equals the run's bit for bit over the whole run, however many misses it
had; :func:`compare_replay` checks every row, and a difference comes back as a
:class:`Divergence` (first cycle, task, signals on both sides, the inputs of that cycle).

Where the replay cannot follow the run (a timing record the run lost, early cycles a
``--keep`` run did not keep), :attr:`ReplayResult.cannot` says why and from where, and
the result is not called equal. Whatever else the run's summary says it lost on the way
(``recording.lost``: signal rows, port values it took but did not log; stale reads its read
log dropped; a recording that stopped) is named in :attr:`ReplayResult.lost`: the replay
compares what the files hold, leaves out the cells the run lost, and never calls the
result equal over data it does not have.

In three parts: :mod:`.logs` reads the run's files, :mod:`.timeline` follows its real timeline,
:mod:`.compare` compares the replay with the run and explains the first difference; this module
puts them together.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path
from typing import Any

from rtloop.app.builder import App
from rtloop.errors import AppError
from rtloop.record.csvfiles import read_reads_csv
from rtloop.record.disk_room import check_room
from rtloop.runtime.replay.compare import Divergence, LostCells, compare_replay, explain
from rtloop.runtime.replay.logs import (
    changed_files,
    load_replay_app,
    lost_on_the_way,
    play_back_devices,
    port_writes,
    read_summary,
    read_timing,
    recording_losses,
    run_end_ns,
    stale_device_note,
    unfinished,
)
from rtloop.runtime.replay.timeline import RunTimeline, check_timeline, timing_lost_at_the_end, window_start
from rtloop.runtime.session import check_out_dir
from rtloop.runtime.simulate import simulate
from rtloop.runtime.snapshot import TaskSnapshot
from rtloop.switching import prepare_reloads, start_codes_of

__all__ = ["ReplayResult", "load_replay_app", "port_writes", "replay", "window_start"]


@dataclass(frozen=True)
class ReplayResult:
    """How the replay compares with the run."""

    rows_in_run: int
    """Rows of the run's signals.csv."""
    rows_compared: int
    """Rows compared and found equal, from the first."""
    divergence: Divergence | None
    """The first difference (None: none among the rows compared)."""
    cannot: str | None = None
    """Why the replay cannot reproduce the run from some point on, and where (None: it can)."""
    skipped_releases: int = 0
    """Releases the run skipped (overruns), followed by the replay."""
    stale_reads: int = 0
    """Stale reads of the run followed by the replay (the samples it actually read)."""
    port_inputs: int = 0
    """Port values the run took, fed back at the cycles that took them."""
    notes: tuple[str, ...] = field(default=())
    from_s: float = 0.0
    """Where the replay starts: 0, or the start of a ``--keep`` run's kept window (a snapshot)."""
    lost: tuple[str, ...] = field(default=())
    """What the run lost on the way (its summary's ``recording``), each with where: the replay
    cannot check it, so the result is never equal while this is not empty."""

    @property
    def equal(self) -> bool:
        """Every row of the run compared, and equal bit for bit (never True when nothing was compared,
        nor when the run lost part of what it did)."""
        return (self.cannot is None and self.divergence is None and not self.lost and self.rows_in_run > 0
                and self.rows_compared == self.rows_in_run)

    @property
    def first_difference_s(self) -> float | None:
        return None if self.divergence is None else self.divergence.t_s


def replay(run_dir: str | Path, out: str | Path, app: App | None = None, *, force: bool = False) -> ReplayResult:
    """Re-simulate the run in ``run_dir`` along its real timeline into ``out``; compare every signal row.

    ``out`` may not be ``run_dir`` nor inside it; a folder holding another run needs ``force``.
    A ``--keep`` run is replayed from the earliest point its files hold the rest of the run
    from: t = 0 if they still do, else the start of its kept window (a snapshot of every task).
    """
    run_dir, out = Path(run_dir), Path(out)
    check_out_dir(out, protect=[run_dir])  # before reading anything: refusals come first
    changed = changed_files(run_dir)
    never_finished = unfinished(run_dir)  # a run killed early may not even have a summary.json
    if never_finished:
        raise AppError(never_finished)
    summary = read_summary(run_dir)
    never_finished = unfinished(run_dir, summary)
    if never_finished:
        raise AppError(never_finished)
    if app is None:
        app, _duration_s = load_replay_app(run_dir)
    start_code = start_codes_of(run_dir / "code")
    for name, spec in app.tasks.items():  # the code the run started with, and reloaded: the run kept both
        prepare_reloads(spec.runnable, run_dir / "code", wait=True, start_codes=start_code.get(name, {}))
    if app.devices:
        play_back_devices(app, run_dir)
    pristine = copy.deepcopy(app)  # runnables as before any prerun, for a second pass
    recording = summary.get("recording") or {}
    periods = {name: task.config.period_ns for name, task in app.tasks.items()}
    cut: list[str] = []
    records, _t0_ns = read_timing(run_dir, periods, cut)
    tasks = summary.get("tasks") or {}
    lost_timing = recording_losses(recording, run_dir).get("timing_records", {})
    dropped = {name: max(int((tasks.get(name) or {}).get("timing_samples_dropped") or 0), lost_timing.get(name, 0))
               for name in periods}
    try:
        reads = read_reads_csv(run_dir / "reads.csv") if (run_dir / "reads.csv").exists() else []
    except ValueError as error:
        raise AppError(str(error)) from None
    notes = [f"{change}: the replay runs it as it is now" for change in changed]
    notes += [stale_device_note(name, device) for name, device in (summary.get("devices") or {}).items()
              if device.get("stale_reads")]
    if app.connections and not (run_dir / "reads.csv").exists():
        notes.append("the run has no reads.csv (recorded by an older rtloop): stale reads are not followed")
    resume: dict[str, TaskSnapshot] = {}
    if recording.get("keep_s") is not None and check_timeline(records, periods, dropped) is not None:
        start = window_start(run_dir, records, periods, dropped)
        if isinstance(start, str):
            return ReplayResult(0, 0, None, cannot=start, notes=tuple(notes),
                                lost=tuple(lost_on_the_way(recording, run_dir)))
        resume = start
    starts = {name: snapshot.next_cycle for name, snapshot in resume.items()}
    from_ns = max((s.at_ns for s in resume.values()), default=0)
    records = {name: [r for r in run if r.cycle >= starts.get(name, 0)] for name, run in records.items()}
    reads = [read for read in reads if read[1] >= starts.get(read[0], 0)]
    writes = {key: value for key, value in port_writes(run_dir).items() if key[1] >= starts.get(key[0], 0)}

    cycles = {name: [r.cycle for r in run] for name, run in records.items()}
    followed = RunTimeline(app, cycles, reads, resume)
    last_release_ns = max((run[-1].release_ns + periods[name] for name, run in records.items() if run), default=0)
    if not last_release_ns:
        raise AppError(f"{run_dir}: timing.csv holds no cycle: nothing to replay")
    replayed_s = (last_release_ns - from_ns) / 1e9  # a --keep window: its span, not the run's
    check_room(app, Path(out), replayed_s, what=f"the replay of {replayed_s:.15g} s",
               remedy="replay into an --out with more room")
    simulate(app, last_release_ns / 1e9, out, port_writes=writes, timeline=followed, force=force,
             protect=(run_dir,))
    gap = check_timeline(records, periods, dropped, starts)
    at_end = timing_lost_at_the_end(records, periods, dropped, run_end_ns(summary, records, periods))
    problems = sorted(followed.problems + ([gap] if gap else []) + at_end)
    recorded_until_ns = None
    if recording.get("stopped"):  # the run went on without its recording: compare up to where every task has it
        recorded_until_ns = min((run[-1].release_ns + periods[name] if run else 0) for name, run in records.items())
        problems = [problem for problem in problems if problem[0] < recorded_until_ns] or [(recorded_until_ns, "")]
    cannot = None
    if problems and problems[0][1]:
        at_ns, why = problems[0]
        cannot = f"from t = {at_ns / 1e9!r} s: {why}"
    skipped = sum(b.cycle - a.cycle - 1 for run in records.values() for a, b in pairwise(run))
    lost = lost_on_the_way(recording, run_dir, recorded_until_ns) + cut
    for task, run in records.items() if not from_ns else ():  # from t = 0 a loss must show in timing.csv
        shown = any(b.cycle != a.cycle + 1 for a, b in pairwise(run)) or any(
            f" of {task}'s timing records" in why for _at, why in at_end)
        if dropped.get(task) and not shown:
            lost.append(f"the run says it lost {dropped[task]} of {task}'s timing records (recording.lost), yet "
                        "timing.csv shows no place they could have been: the replay cannot tell what they were")
    common: dict[str, Any] = {"cannot": cannot, "skipped_releases": skipped, "stale_reads": len(reads),
                              "port_inputs": sum(len(v) for v in writes.values()), "notes": tuple(notes),
                              "from_s": from_ns / 1e9, "lost": tuple(lost)}
    if not (run_dir / "signals.csv").exists():
        return ReplayResult(0, 0, None, **{**common, "cannot": cannot or "the run recorded no signals.csv: "
                                           "nothing to compare"})
    until_ns = problems[0][0] if problems else None
    lost_cells = LostCells()
    rows, equal_rows, divergence = compare_replay(run_dir / "signals.csv", out / "signals.csv", app, until_ns,
                                                  from_ns, lost_cells, cut)
    common["lost"] += tuple(line for line in cut if line not in common["lost"])
    if lost_cells.rows:
        common["lost"] += (lost_cells.describe(recording_losses(recording, run_dir).get("signal_rows", {})),)
    if not rows and common["cannot"] is None:
        common["cannot"] = "the run's signals.csv holds no rows: nothing to compare"
    if divergence is not None and divergence.task:
        again = RunTimeline(pristine, cycles, reads, resume)
        divergence = explain(divergence, again, out, writes, records, periods)
    if divergence is not None and changed:
        divergence = dataclasses.replace(divergence, changed_files=tuple(changed))
    return ReplayResult(rows, equal_rows, divergence, **common)
