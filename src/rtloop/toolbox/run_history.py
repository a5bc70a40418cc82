"""The runs a service keeps: before every start, ``latest/`` is set aside under a number, and
the history is pruned to a bounded count (``rtloop service``'s unit runs this as ExecStartPre).

In a restart burst (a drive that faults at start-up: fail, restart a second later, fail
again, five times) the first failure is usually the informative one; the later ones often
fail differently ("configure failed", a device still held). So a run set aside is named by
how it ended, and the first failure after a clean run is marked so pruning spares it:

    latest/                  the run going on (or the last one, the service stopped)
    run-0007-failed/         a later failure of a burst: pruned before the first one
    run-0006-first-failure/  the first failure after a clean run (or after none)
    run-0005-clean/          ended by its duration, a stop or a requested stop: pruned first

At most ``MAX_RUNS_KEPT`` runs are kept besides ``latest/``. Over that, the oldest clean runs
go first, then the oldest later failures, then the oldest first failures; the newest
``ALWAYS_KEPT`` are never pruned (the run before the one starting is always there).

    python -m rtloop.toolbox.run_history /var/lib/rtloop/jiwy/latest
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import stat
import sys
from dataclasses import dataclass
from pathlib import Path

MAX_RUNS_KEPT = 8
"""Runs kept besides ``latest/``; each holds at most its ``--keep`` seconds plus the cycles around faults."""
ALWAYS_KEPT = 2
"""The newest runs set aside are never pruned (so the run before any start is there to read)."""
OUTCOMES = ("clean", "failed", "first-failure")
"""How a run set aside ended, in the order pruning takes them."""
MAX_SUMMARY_BYTES = 4 << 20
FAILED_STOPS = {"fault", "watchdog", "running"}
"""``stopped_by`` of a run that failed (``running``: it never wrote its final summary: killed, crashed)."""


@dataclass(frozen=True, slots=True)
class PastRun:
    """A run set aside: ``run-NNNN-OUTCOME/`` beside ``latest/``."""

    number: int
    outcome: str
    path: Path


def history_prefix(latest: Path) -> str:
    """``run-`` beside a ``latest/`` folder, ``NAME.run-`` beside any other (``--out /srv/robot/NAME``)."""
    return "run-" if latest.name == "latest" else f"{latest.name}.run-"


def past_runs(latest: Path) -> list[PastRun]:
    """The runs set aside beside ``latest``, oldest first (folders only: a link is never ours)."""
    pattern = re.compile(re.escape(history_prefix(latest)) + r"(\d+)-(" + "|".join(OUTCOMES) + r")")
    runs = []
    try:
        entries = list(os.scandir(latest.parent))
    except FileNotFoundError:
        return []
    for entry in entries:
        match = pattern.fullmatch(entry.name)
        if match and entry.is_dir(follow_symlinks=False):
            runs.append(PastRun(int(match.group(1)), match.group(2), Path(entry.path)))
    return sorted(runs, key=lambda run: run.number)


def ended_cleanly(run_dir: Path) -> bool:
    """Whether the run's summary.json says it ended by its duration or a stop; no summary (a
    crash, a kill before the first one) or one that is not to be read counts as a failure."""
    try:
        fd = os.open(run_dir / "summary.json", os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:
        return False
    with open(fd, "rb") as file:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return False
        data = file.read(MAX_SUMMARY_BYTES + 1)
    try:
        summary = json.loads(data)
    except (ValueError, RecursionError):
        return False
    if not isinstance(summary, dict) or summary.get("running") is not False:
        return False
    stopped_by = summary.get("stopped_by")
    return isinstance(stopped_by, str) and stopped_by not in FAILED_STOPS


def outcome_of(run_dir: Path, previous: PastRun | None) -> str:
    """``clean``, or a failure: ``first-failure`` when the run before ended cleanly (or there was none)."""
    if ended_cleanly(run_dir):
        return "clean"
    return "failed" if previous is not None and previous.outcome != "clean" else "first-failure"


def runs_to_prune(runs: list[PastRun], most: int = MAX_RUNS_KEPT, always: int = ALWAYS_KEPT) -> list[PastRun]:
    """Which of ``runs`` (oldest first) to delete to keep ``most``: clean ones, then later failures,
    then first failures, each oldest first; never the newest ``always``."""
    excess = len(runs) - most
    if excess <= 0:
        return []
    candidates = runs[:-always] if always else runs
    ordered = sorted(candidates, key=lambda run: (OUTCOMES.index(run.outcome), run.number))
    return ordered[:excess]


def set_aside(latest: Path, most: int = MAX_RUNS_KEPT) -> list[str]:
    """Move ``latest`` (and a ``previous/`` of the older two-run scheme) into the numbered history,
    then prune it; returns what was done, one line each (for the journal)."""
    done = []
    runs = past_runs(latest)
    legacy = latest.with_name("previous" if latest.name == "latest" else f"{latest.name}.previous")
    for folder in (legacy, latest):
        if folder.is_symlink() or not folder.is_dir():
            continue
        previous = runs[-1] if runs else None
        number = previous.number + 1 if previous else 1
        outcome = outcome_of(folder, previous)
        run = PastRun(number, outcome, folder.with_name(f"{history_prefix(latest)}{number:04d}-{outcome}"))
        os.rename(folder, run.path)
        runs.append(run)
        done.append(f"kept {folder.name}/ as {run.path.name}/")
    for run in runs_to_prune(runs, most):
        shutil.rmtree(run.path)  # removes links inside, never what they point to
        done.append(f"removed {run.path.name}/ (at most {most} runs kept)")
    return done


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rtloop.toolbox.run_history",
                                     description="Set a service's latest run aside and prune the history.")
    parser.add_argument("latest", type=Path, help="the folder the next run records into (its --out)")
    parser.add_argument("--runs-kept", type=int, default=MAX_RUNS_KEPT, metavar="N",
                        help=f"runs kept besides LATEST (default {MAX_RUNS_KEPT})")
    args = parser.parse_args(argv)
    if args.runs_kept < ALWAYS_KEPT:
        print(f"run_history: --runs-kept must be at least {ALWAYS_KEPT}, got {args.runs_kept}", file=sys.stderr)
        return 2
    try:
        for line in set_aside(args.latest, args.runs_kept):
            print(f"run_history: {line}")
    except OSError as error:
        print(f"run_history: {args.latest}: {error.strerror or error}"
              + (f" ({error.filename})" if error.filename else ""), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
