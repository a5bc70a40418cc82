"""Helpers shared by the benchmark scripts: statistics, tables, machine facts, a no-op task, and the
options, result head, closing sections and output every table-printing benchmark ends with.

Imported by the benchmarks (in the parent process and, through ``multiprocessing``'s spawn
re-import, in the task processes), so it imports nothing heavier than numpy and rtloop.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rtloop import Runnable
from rtloop.linux import rt

PERCENTILES = (("min", 0.0), ("p50", 50.0), ("p99", 99.0), ("p99.9", 99.9), ("max", 100.0))
STAT_COLUMNS = tuple(name for name, _ in PERCENTILES)

# rtloop at commit 7c2e45a calls ``rt.now_ns`` (task.py, supervisor.py) but rt.py no longer
# defines it (the import `from time import monotonic_ns as now_ns` was dropped), so every
# App.run fails at its first cycle with AttributeError. The benchmarks put the same
# function back — exactly what rt.py used to import — so they measure the loop as designed.
# The shim is reported in the output; remove it once rt.py defines now_ns again.
RT_NOW_NS_SHIMMED = not hasattr(rt, "now_ns")
if RT_NOW_NS_SHIMMED:
    rt.now_ns = time.monotonic_ns  # type: ignore[attr-defined]


class NoOp(Runnable):
    """A step that does nothing: what is left is the framework's own cost."""

    def __init__(self, n_inputs: int = 0, n_outputs: int = 0) -> None:
        self.n_inputs = n_inputs
        self.n_outputs = n_outputs

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        pass


def stats_us(values_ns: Iterable[float] | np.ndarray) -> dict[str, float]:
    """min/p50/p99/p99.9/max of nanosecond values, in microseconds (NaN when empty)."""
    data = np.asarray(values_ns, dtype=np.float64)
    if data.size == 0:
        return {name: float("nan") for name in STAT_COLUMNS}
    values = np.percentile(data, [q for _, q in PERCENTILES])
    return {name: float(v) / 1000.0 for (name, _), v in zip(PERCENTILES, values, strict=True)}


def median_us_per_call(call: Callable[[], object], repeats: int, batches: int = 11,
                       before_batch: Callable[[], object] | None = None) -> float:
    """Median over ``batches`` batches of ``repeats`` calls of the time per call, in µs (perf_counter;
    ``before_batch``, untimed, runs before each batch: e.g. to empty a ring the calls fill)."""
    samples = []
    for _ in range(batches):
        if before_batch is not None:
            before_batch()
        started = time.perf_counter_ns()
        for _ in range(repeats):
            call()
        samples.append((time.perf_counter_ns() - started) / repeats)
    return float(np.median(samples)) / 1000


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    """A GitHub markdown table; floats get 2 decimals, the first column is left-aligned."""

    def cell(value: Any) -> str:
        if isinstance(value, float):
            return "n/a" if np.isnan(value) else f"{value:.2f}"
        return str(value)

    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] + ["---:"] * (len(header) - 1)) + "|"]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def machine_facts() -> dict[str, Any]:
    """What the numbers depend on: kernel, CPU, preemption model, load, date."""
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    virtualization = []
    for flag in ("--vm", "--container"):
        try:
            found = subprocess.run(["systemd-detect-virt", flag], capture_output=True, text=True, check=False)
        except OSError:
            break
        if found.stdout.strip() not in ("", "none"):
            virtualization.append(f"{flag[2:]}: {found.stdout.strip()}")
    return {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "kernel": platform.release(),
        "preemption": rt.preemption_model(),
        "cpu_model": model,
        "cpus": os.cpu_count(),
        "virtualization": ", ".join(virtualization) or "none detected",
        "python": platform.python_version(),
        "loadavg_at_start": Path("/proc/loadavg").read_text().split()[:3],
        "rt_runtime_us": Path("/proc/sys/kernel/sched_rt_runtime_us").read_text().strip(),
        "isolated_cpus": Path("/sys/devices/system/cpu/isolated").read_text().strip() or "none",
        "rtloop_rt_now_ns_shim": RT_NOW_NS_SHIMMED,
    }


def facts_markdown(facts: dict[str, Any]) -> str:
    return "\n".join(f"- {key}: {value}" for key, value in facts.items())


class PmQos(rt.CpuDmaLatency):
    """rtloop's own hold on /dev/cpu_dma_latency at 0 µs (as cyclictest holds it for itself), held for the
    whole benchmark so that every contender runs under the same power management setting (not only
    cyclictest's blocks); ``enabled=False`` (``--no-pm-qos``) leaves it alone."""

    def __init__(self, enabled: bool) -> None:
        super().__init__()
        self.enabled = enabled

    def __enter__(self) -> PmQos:
        if self.enabled:
            super().__enter__()
        return self

    @property
    def active(self) -> bool:
        return self.held


def write_json(path: str | Path, data: dict[str, Any]) -> None:
    Path(path).write_text(json.dumps(data, indent=2, default=float) + "\n")


def where_measured() -> str:
    """One line naming the host, its kernel and the Python that measured (the device benchmarks' heading)."""
    return f"{platform.node()}: {platform.release()}, Python {sys.version.split()[0]}"


QUICK_ROUNDS, QUICK_BLOCK_S = 2, 3.0


def add_output_options(parser: argparse.ArgumentParser, quick_help: str | None = None) -> None:
    """The options a benchmark's command line ends with: ``--quick`` (where ``quick_help`` says what it
    runs: ``QUICK_ROUNDS`` rounds of ``QUICK_BLOCK_S`` s blocks) and ``--json PATH``."""
    if quick_help is not None:
        parser.add_argument("--quick", action="store_true", help=quick_help)
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")


def parse_options(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """The parsed command line, with ``--quick`` (if the parser has it) setting rounds and block length."""
    args = parser.parse_args(argv)
    if getattr(args, "quick", False):
        args.rounds, args.block_s = QUICK_ROUNDS, QUICK_BLOCK_S
    return args


def result_head(benchmark: str, args: argparse.Namespace, facts: dict[str, Any], started: float) -> dict[str, Any]:
    """What every result starts with: its name, the command, the settings (not where the JSON went),
    the machine and the time it took since ``started`` (``time.monotonic()``)."""
    return {
        "benchmark": benchmark,
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "settings": {k: v for k, v in vars(args).items() if k != "json"},
        "machine": facts,
        "elapsed_s": round(time.monotonic() - started, 1),
    }


TARGET_RESULT = {True: "met", False: "**MISSED**", None: "—"}  # None: a figure given for information


def closing_sections(result: dict[str, Any]) -> list[str]:
    """The "### Targets" table (where the result has targets) and the "### Machine" facts, as sections."""
    sections = []
    if "targets" in result:
        sections += ["### Targets", markdown_table(["target", "measured", "result"],
                                                   [[t["target"], t["measured"], TARGET_RESULT[t["met"]]]
                                                    for t in result["targets"]])]
    return [*sections, "### Machine", facts_markdown(result["machine"])]


def print_and_save(markdown: str, result: dict[str, Any], json_path: str | None) -> int:
    """Print the tables, write the result as JSON where ``--json`` asked; the exit status (0)."""
    print(markdown)
    if json_path:
        write_json(json_path, result)
    return 0


def load_timing_csv(path: Path) -> dict[str, np.ndarray]:
    """timing.csv → {task: n × 4 int64 array (cycle, release, start, end)} in cycle order."""
    per_task: dict[str, list[list[int]]] = {}
    with open(path) as file:
        next(file)
        for line in file:
            task, *numbers = line.rstrip("\n").split(",")
            per_task.setdefault(task, []).append([int(n) for n in numbers])
    out = {}
    for task, rows in per_task.items():
        records = np.array(rows, dtype=np.int64).reshape(-1, 4)
        out[task] = records[np.argsort(records[:, 0], kind="stable")]
    return out


def trim(records: np.ndarray, count: int) -> np.ndarray:
    """Drop the first and last ``count`` rows (start-up and shut-down), as rtloop's summary does."""
    if count <= 0:
        return records
    return records[count:-count] if len(records) > 2 * count else records[:0]


@contextlib.contextmanager
def summary_synced_every_rewrite(active: bool = True) -> Iterator[None]:
    """While inside, rtloop syncs summary.json at every rewrite of a running run, as it did before issue 33
    (since then only the first and the final one): a before/after comparison in one checkout, one process."""
    from rtloop.record import summary

    written = summary.write_new

    def synced(path: Path, data: bytes, *, sync: bool = False) -> None:
        written(path, data, sync=True)

    if active:
        summary.write_new = synced
    try:
        yield
    finally:
        summary.write_new = written
