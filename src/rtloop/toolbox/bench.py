"""The thesis's chapter-6 experiments (section 6.3) on this machine: the engine of ``rtloop bench``.

Three experiments (:data:`rtloop.toolbox.bench_choices.EXPERIMENTS`; :mod:`rtloop.cli.bench` describes them and is the
command line): two primes tasks on one core and on two, one task with and without
``stress-ng`` load, a no-op task beside ``cyclictest``. Each run is an ordinary run
directory; each experiment writes ``table.md``, ``bench.json`` and, through
:attr:`Settings.write_report`, a comparison report into its directory. The runnables live
here, at module level, so the spawned task processes can import them.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.app.builder import App
from rtloop.errors import RtloopError
from rtloop.linux import rt
from rtloop.runnable import Runnable
from rtloop.stats import timing
from rtloop.toolbox.bench_choices import DEFAULT_STRESS, STRESSORS

PERIOD_NS = 1_000_000
"""1 kHz, as in the thesis."""
HIGH_PRIORITY, LOW_PRIORITY = 80, 79
PRIMES_LIMIT = 700
"""The thesis's load: primes up to 700 every period (section 6.3.1)."""


class BenchError(RtloopError, RuntimeError):
    """An experiment failed while it ran (a tool it started exited with an error): exit 1."""


class BenchRefused(BenchError, ValueError):
    """The benchmark cannot run here as asked (no RT privilege, a tool missing, one CPU, ...): bad input, exit 2."""


# --- the runnables (module level: the task processes import them) --------------------------------
class Primes(Runnable):
    """Counts the primes up to ``limit`` by trial division, once per period (the thesis's load).

    Output ``y[0]``: how many primes were found (125 for a limit of 700).
    """

    n_inputs = 0
    n_outputs = 1

    def __init__(self, limit: int = PRIMES_LIMIT) -> None:
        self.limit = limit

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        count = 0
        for candidate in range(2, self.limit + 1):
            divisor = 2
            while divisor * divisor <= candidate:
                if candidate % divisor == 0:
                    break
                divisor += 1
            else:
                count += 1
        y[0] = count


class NoOp(Runnable):
    """A step that does nothing: what remains is wake-up latency and the loop's own cost."""

    n_inputs = 0
    n_outputs = 0

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        pass


# --- settings and results ------------------------------------------------------------------------
@dataclass(frozen=True)
class Settings:
    """What the command line asked for, resolved against this machine."""

    duration_s: float
    """Seconds per run."""
    out: Path
    """The experiment's directory."""
    cpu: int
    """The measured core (the stressed one; the shared one in ``same-core``)."""
    other_cpu: int
    """A second core (the first task's core in ``different-cores``)."""
    policy: str
    """``fifo``, or ``other`` with ``--allow-non-rt`` where real time is not allowed."""
    stressors: tuple[str, ...] = DEFAULT_STRESS
    """stress-ng stressor groups for ``stress`` (keys of :data:`STRESSORS`)."""
    stress_task: str = "primes"
    """The task measured under stress: ``primes`` or ``noop``."""
    trim: int = timing.DEFAULT_TRIM
    """Cycles left out at each end of the distributions."""
    write_report: Callable[[list[Path], Path], Path | None] | None = None
    """Writes the comparison report of run directories into a folder; its file (None: no report)."""

    def priority(self, wanted: int) -> int:
        """The priority to ask for: ``wanted`` under fifo, 0 under other."""
        return wanted if self.policy == "fifo" else 0


@dataclass(frozen=True)
class Row:
    """One line of a comparison table: one task in one run."""

    run: str
    task: str
    cpu: int | None
    policy: str
    priority: int
    cycles: int
    latency_p50_us: float
    latency_p99_us: float
    latency_max_us: float
    exec_p50_us: float
    deadline_misses: int | str
    overruns: int | str
    jitter_over_3pct: int


COLUMNS = ("run", "task", "cpu", "policy/prio", "cycles", "latency p50 µs", "p99 µs", "max µs", "exec p50 µs",
           "deadline misses", "overruns", "jitter > 3 %")


@dataclass
class Outcome:
    """What one experiment produced."""

    name: str
    out: Path
    rows: list[Row] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    report: Path | None = None

    def markdown(self) -> str:
        """The experiment's table and notes as markdown."""
        notes = [f"- {note}" for note in self.notes]
        if self.report is not None:
            notes.append(f"- report: {self.report}")
        return "\n\n".join([f"### {self.name} ({self.out})", markdown_table(self.rows), "\n".join(notes)]).rstrip()


# --- tables --------------------------------------------------------------------------------------
def _us(value_ns: float | None) -> float:
    return float("nan") if value_ns is None else value_ns / 1000.0


def rows_from_summary(run: str, summary: dict[str, Any]) -> list[Row]:
    """One :class:`Row` per task of a parsed ``summary.json``."""
    rows = []
    for task, stats in summary["tasks"].items():
        latency, exec_ns = stats["latency_ns"], stats["exec_ns"]
        rows.append(Row(run, task, stats["cpu"], stats["policy"], stats["priority"], stats["cycles"],
                        _us(latency["p50"]), _us(latency["p99"]), _us(latency["max"]), _us(exec_ns["p50"]),
                        stats["deadline_misses"], stats["overruns"], stats["jitter_over_3pct"]))
    return rows


def rows_from_run(run_dir: Path) -> list[Row]:
    """Rows of a run directory (read from its ``summary.json``, the artifact contract)."""
    return rows_from_summary(run_dir.name, json.loads((run_dir / "summary.json").read_text()))


def _cell(value: object) -> str:
    if isinstance(value, float):
        return "n/a" if np.isnan(value) else f"{value:.1f}"
    return "—" if value is None else str(value)


def markdown_table(rows: Sequence[Row]) -> str:
    """A GitHub markdown table of rows (µs with one decimal)."""
    lines = ["| " + " | ".join(COLUMNS) + " |", "|---|---|" + "---:|" * (len(COLUMNS) - 2)]
    for r in rows:
        cells = [r.run, r.task, r.cpu, f"{r.policy}/{r.priority}", r.cycles, r.latency_p50_us, r.latency_p99_us,
                 r.latency_max_us, r.exec_p50_us, r.deadline_misses, r.overruns, r.jitter_over_3pct]
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return "\n".join(lines)


# --- helpers -------------------------------------------------------------------------------------
def progress(message: str) -> None:
    """A progress line on stderr (the tables go to stdout)."""
    print(f"rtloop bench: {message}", file=sys.stderr, flush=True)


PF_KTHREAD = 0x00200000
RT_POLICIES = {1: "FIFO", 2: "RR", 6: "DEADLINE"}


def _thread_stat(stat_path: Path) -> tuple[str, int, int, int] | None:
    """(comm, flags, rt_priority, policy) of one thread from its ``stat`` file, None if it is gone."""
    try:
        text = stat_path.read_text()
    except OSError:
        return None
    comm = text[text.index("(") + 1 : text.rindex(")")]
    fields = text[text.rindex(")") + 2 :].split()  # fields[0] is field 3 of proc(5)
    return comm, int(fields[6]), int(fields[37]), int(fields[38])


def rt_neighbours(cpus: set[int]) -> list[str]:
    """User-space real-time threads (not ours) allowed on ``cpus``: they preempt or delay the measured tasks."""
    found = []
    for stat_path in Path("/proc").glob("[0-9]*/task/[0-9]*/stat"):
        pid, tid = int(stat_path.parts[2]), int(stat_path.parts[4])
        stat = _thread_stat(stat_path)
        if pid == os.getpid() or stat is None or stat[1] & PF_KTHREAD or stat[3] not in RT_POLICIES:
            continue
        try:
            allowed = os.sched_getaffinity(tid)
        except OSError:
            continue
        if allowed & cpus:
            found.append(f"pid {pid} {stat[0]} {RT_POLICIES[stat[3]]} {stat[2]} on cpus {sorted(allowed)}")
    return found


def warn_neighbours(settings: Settings, when: str) -> list[str]:
    """Warn (and return a note) if other real-time threads share the measured cores."""
    found = rt_neighbours({settings.cpu, settings.other_cpu})
    if not found:
        return []
    shown = "; ".join(found[:4]) + (f"; and {len(found) - 4} more" if len(found) > 4 else "")
    progress(f"  WARNING: other real-time threads on the measured cores {when}: {shown}")
    return [f"other real-time threads were running {when} (results include their interference): {shown}"]


def run_app(app: App, settings: Settings, out: Path, notes: list[str]) -> list[Row]:
    """Run ``app`` for the set duration into ``out``; its rows; warn if a task was not real-time or had company."""
    notes += warn_neighbours(settings, f"before {out.name}")
    from rtloop.runtime.supervisor import run  # here: the experiments' names are read by every `rtloop` command

    started = time.monotonic()
    run(app, settings.duration_s, out, trim=settings.trim)
    rows = rows_from_run(out)
    progress(f"  {out.name}: done in {time.monotonic() - started:.1f} s → {out}")
    notes += warn_neighbours(settings, f"after {out.name}")
    if settings.policy == "fifo":
        summary = json.loads((out / "summary.json").read_text())
        for task, stats in summary["tasks"].items():
            if not stats["rt"]:
                progress(f"  WARNING: task {task} in {out.name} was not real-time: {stats['rt_reason']}")
    return rows


def write_outcome(outcome: Outcome, run_dirs: list[Path], settings: Settings) -> Outcome:
    """Comparison report of the runs, ``table.md`` and ``bench.json`` in the experiment's directory."""
    if settings.write_report is not None:
        outcome.report = settings.write_report(run_dirs, outcome.out)
    (outcome.out / "table.md").write_text(outcome.markdown() + "\n")
    record = {"experiment": outcome.name, "runs": [str(p) for p in run_dirs], "notes": outcome.notes,
              "rows": [row.__dict__ for row in outcome.rows]}
    (outcome.out / "bench.json").write_text(json.dumps(record, indent=2, default=str) + "\n")
    return outcome


def bench_app_name(run: str) -> str:
    """The app name of one run: a live app's name is its user's alone, and another bench (another checkout's
    test, another terminal) may run at the same time; its threads are noted as neighbours, not refused."""
    return f"{run}_{os.getpid()}"


# --- affinity (thesis 6.3.1) ---------------------------------------------------------------------
def primes_pair_app(name: str, settings: Settings, cpus: tuple[int, int]) -> App:
    """Two primes tasks, priorities 80 and 79, on ``cpus``."""
    app = App(bench_app_name(name))
    for index, (cpu, priority) in enumerate(zip(cpus, (HIGH_PRIORITY, LOW_PRIORITY), strict=True), start=1):
        app.add_task(f"primes{index}", Primes(PRIMES_LIMIT), period_ns=PERIOD_NS,
                     priority=settings.priority(priority), cpu=cpu, policy=settings.policy)
    return app


def run_affinity(settings: Settings) -> Outcome:
    """Two primes tasks on the same core, then on different cores."""
    outcome = Outcome("affinity", settings.out)
    layouts = {"same-core": (settings.cpu, settings.cpu), "different-cores": (settings.other_cpu, settings.cpu)}
    run_dirs = []
    for label, cpus in layouts.items():
        progress(f"  {label}: primes1 (prio {HIGH_PRIORITY}) on cpu {cpus[0]}, primes2 (prio {LOW_PRIORITY}) "
                 f"on cpu {cpus[1]}, {settings.duration_s:g} s")
        run_dir = settings.out / label
        app = primes_pair_app(label.replace("-", "_"), settings, cpus)
        outcome.rows += run_app(app, settings, run_dir, outcome.notes)
        run_dirs.append(run_dir)
        outcome.notes.append(f"{label}: cpus {cpus[0]},{cpus[1]}")
    outcome.notes.append(f"primes up to {PRIMES_LIMIT} every {PERIOD_NS // 1000} µs; primes1 priority "
                         f"{settings.priority(HIGH_PRIORITY)}, primes2 {settings.priority(LOW_PRIORITY)} "
                         f"({settings.policy})")
    return write_outcome(outcome, run_dirs, settings)


# --- stress (thesis 6.3.2) -----------------------------------------------------------------------
def stress_command(settings: Settings) -> list[str]:
    """stress-ng pinned to the measured core, SCHED_OTHER (as in the thesis), stopping by itself later."""
    command = ["stress-ng", "--taskset", str(settings.cpu), "--sched", "other",
               "--timeout", f"{int(settings.duration_s) + 30}s", "--quiet"]
    for name in settings.stressors:
        command += STRESSORS[name]
    return command


def single_task_app(name: str, settings: Settings, runnable: Runnable, task: str) -> App:
    """One task at priority 80 on the measured core."""
    app = App(bench_app_name(name))
    app.add_task(task, runnable, period_ns=PERIOD_NS, priority=settings.priority(HIGH_PRIORITY), cpu=settings.cpu,
                 policy=settings.policy)
    return app


def stress_runnable(settings: Settings) -> Runnable:
    return Primes(PRIMES_LIMIT) if settings.stress_task == "primes" else NoOp()


def start_stress(command: list[str]) -> subprocess.Popen[bytes]:
    """Start stress-ng in its own session (so its workers can be stopped together) and let it spin up."""
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    time.sleep(1.0)
    if process.poll() is not None:
        error = process.stderr.read().decode(errors="replace").strip() if process.stderr else ""
        raise BenchError(f"stress-ng exited at once (status {process.returncode}): {error or ' '.join(command)}")
    return process


def stop_stress(process: subprocess.Popen[bytes]) -> None:
    """SIGTERM to the stress-ng session started above; SIGKILL if it lingers."""
    try:
        os.killpg(process.pid, signal.SIGTERM)
        process.wait(timeout=10)
    except ProcessLookupError:
        pass
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    if process.stderr:
        process.stderr.close()


def run_stress(settings: Settings) -> Outcome:
    """One task alone on its core, then with stress-ng load pinned to that core."""
    outcome = Outcome("stress", settings.out)
    task = settings.stress_task
    command = stress_command(settings)
    run_dirs = [settings.out / "quiet", settings.out / "stressed"]
    progress(f"  quiet: {task} (prio {HIGH_PRIORITY}) on cpu {settings.cpu}, {settings.duration_s:g} s")
    quiet = single_task_app("quiet", settings, stress_runnable(settings), task)
    outcome.rows += run_app(quiet, settings, run_dirs[0], outcome.notes)
    progress(f"  stressed: same, with `{' '.join(command)}`, {settings.duration_s:g} s")
    stress = start_stress(command)
    try:
        stressed = single_task_app("stressed", settings, stress_runnable(settings), task)
        outcome.rows += run_app(stressed, settings, run_dirs[1], outcome.notes)
    finally:
        stop_stress(stress)
    outcome.notes.append(f"task {task} on cpu {settings.cpu}, priority {settings.priority(HIGH_PRIORITY)} "
                         f"({settings.policy}), period {PERIOD_NS // 1000} µs")
    outcome.notes.append(f"stressed: `{' '.join(command)}` (stopped when the run ended)")
    return write_outcome(outcome, run_dirs, settings)


# --- cyclictest ----------------------------------------------------------------------------------
CYCLICTEST_SAMPLE = re.compile(r"^\s*0:\s*(\d+):\s*(\d+)\s*$")


def cyclictest_command(settings: Settings, loops: int, json_path: Path) -> list[str]:
    """cyclictest with one thread on the measured core, same period and priority as the no-op task.

    ``-v -N`` prints every sample in nanoseconds (no histogram bins), so the statistics are
    computed exactly as rtloop's; ``--json`` keeps cyclictest's own summary.
    """
    fifo = settings.policy == "fifo"
    scheduling = ["-m", "-p", str(HIGH_PRIORITY)] if fifo else ["--policy=other", "-p", "0"]
    return ["cyclictest", *scheduling, "-a", str(settings.cpu), "-t", "1", "-i", str(PERIOD_NS // 1000),
            "-l", str(loops), "-q", "-v", "-N", f"--mainaffinity={settings.other_cpu}", f"--json={json_path}"]


def parse_cyclictest_samples(text: str) -> timing.TimingSamples:
    """``-v -N`` output → timing samples: release k·P, start = release + latency, end = start."""
    pairs = [(int(m.group(1)), int(m.group(2))) for line in text.splitlines() if (m := CYCLICTEST_SAMPLE.match(line))]
    cycles = np.array([p[0] for p in pairs], dtype=np.int64)
    latency = np.array([p[1] for p in pairs], dtype=np.int64)
    release = cycles * PERIOD_NS
    start = release + latency
    return timing.TimingSamples(cycles, release, start, start.copy())


def cyclictest_row(samples: timing.TimingSamples, settings: Settings) -> Row:
    """A table row for cyclictest, from rtloop's own statistics functions (no step: exec 0)."""
    stats = timing.task_timing(samples, PERIOD_NS, trim=settings.trim)
    return Row("cyclictest", "cyclictest", settings.cpu, settings.policy, settings.priority(HIGH_PRIORITY),
               stats.cycles, _us(stats.latency_ns.p50), _us(stats.latency_ns.p99), _us(stats.latency_ns.max),
               float("nan"), stats.deadline_misses, "n/a", stats.jitter_over_3pct)


def run_cyclictest_block(settings: Settings) -> Row:
    """Run cyclictest for the set duration; write its text and JSON; its row."""
    out = settings.out / "cyclictest"
    out.mkdir(parents=True, exist_ok=True)
    loops = max(1, round(settings.duration_s * 1e9 / PERIOD_NS))
    command = cyclictest_command(settings, loops, out / "cyclictest.json")
    progress(f"  cyclictest: `{' '.join(command)}`")
    started = time.monotonic()
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    (out / "cyclictest.txt").write_text(result.stdout + result.stderr)
    if result.returncode != 0:
        raise BenchError(f"cyclictest failed (status {result.returncode}): {result.stderr.strip()[-500:]}")
    samples = parse_cyclictest_samples(result.stdout)
    row = cyclictest_row(samples, settings)
    (out / "samples.json").write_text(json.dumps({"command": command, "row": row.__dict__}, indent=2,
                                                 default=str) + "\n")
    progress(f"  cyclictest: done in {time.monotonic() - started:.1f} s → {out}")
    return row


def run_cyclictest(settings: Settings) -> Outcome:
    """A no-op rtloop task, then cyclictest, same priority, core and period."""
    outcome = Outcome("cyclictest", settings.out)
    run_dir = settings.out / "rtloop"
    progress(f"  rtloop: no-op task (prio {HIGH_PRIORITY}) on cpu {settings.cpu}, {settings.duration_s:g} s")
    outcome.rows += run_app(single_task_app("noop", settings, NoOp(), "noop"), settings, run_dir, outcome.notes)
    outcome.rows.append(run_cyclictest_block(settings))
    outcome.notes.append(f"both on cpu {settings.cpu}, priority {settings.priority(HIGH_PRIORITY)} "
                         f"({settings.policy}), period {PERIOD_NS // 1000} µs, one after the other")
    outcome.notes.append("cyclictest rows use rtloop's statistics on its -v -N samples; its 'deadline misses' are "
                         "wake-ups later than one period, it has no step (exec n/a) and no overrun count")
    outcome.notes.append(f"cyclictest output: {settings.out / 'cyclictest'}/cyclictest.txt and cyclictest.json")
    return write_outcome(outcome, [run_dir], settings)


RUNNERS: dict[str, Callable[[Settings], Outcome]] = {
    "affinity": run_affinity,
    "stress": run_stress,
    "cyclictest": run_cyclictest,
}
RUNS_PER_EXPERIMENT = {"affinity": 2, "stress": 2, "cyclictest": 2}


# --- the machine ----------------------------------------------------------------------------------
def choose_cpus(requested: int | None) -> tuple[int, int]:
    """(measured core, another core): by default the highest allowed CPU and the lowest other one."""
    available = sorted(os.sched_getaffinity(0))
    if len(available) < 2:
        raise BenchRefused(f"the experiments need two CPUs; this process may use only {available}")
    cpu = available[-1] if requested is None else requested
    if cpu not in available:
        raise BenchRefused(f"--cpu {cpu}: not one of this process's CPUs {available}")
    return cpu, min(c for c in available if c != cpu)


def choose_policy(allow_non_rt: bool) -> str:
    """``fifo`` if real time is allowed; ``other`` with ``--allow-non-rt``; else a clear refusal."""
    capabilities = rt.probe()
    if capabilities.may_use_rt:
        return "fifo"
    if not allow_non_rt:
        raise BenchRefused(f"real-time scheduling is not allowed here ({capabilities.rt_reason}); run as root "
                         "(sudo), grant CAP_SYS_NICE or an RLIMIT_RTPRIO, or pass --allow-non-rt to run "
                         "under SCHED_OTHER anyway")
    progress(f"NOT REAL-TIME: {capabilities.rt_reason}; --allow-non-rt: every task and cyclictest run under "
             "SCHED_OTHER, priority 0 (the priorities 80/79 of the affinity experiment do not apply)")
    return "other"


def check_tools(experiments: Sequence[str]) -> None:
    """The external programs an experiment needs, with the package that has them."""
    needs = {"stress": ("stress-ng", "stress-ng"), "cyclictest": ("cyclictest", "rt-tests")}
    for experiment in experiments:
        if experiment in needs and shutil.which(needs[experiment][0]) is None:
            program, package = needs[experiment]
            raise BenchRefused(f"{experiment}: {program} not found; install the {package} package "
                             f"(Debian/Ubuntu: sudo apt-get install {package})")
