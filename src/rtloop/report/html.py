"""One self-contained ``report.html``: tables, warnings and the PNGs as data URIs."""

from __future__ import annotations

import base64
from collections.abc import Sequence
from dataclasses import dataclass
from html import escape
from pathlib import Path
from typing import Any

from rtloop.report.data import Run
from rtloop.text import counted, user_frames

STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em auto; padding: 0 1em; max-width: 1320px; color: #222; }
h1 { font-size: 1.6em; } h2 { border-bottom: 2px solid #ccc; padding-bottom: .2em; margin-top: 2em; }
table { border-collapse: collapse; margin: .8em 0; font-size: .9em; }
th, td { border: 1px solid #ccc; padding: .25em .6em; text-align: right; }
th { background: #f0f0f0; } td.name, th.name { text-align: left; }
.bad { background: #fde2e1; } .ok { background: #e3f6e3; } .amber { background: #fff4d6; }
.criterion { font-weight: 600; } .scroll { overflow-x: auto; max-width: 100%; }
.banner { padding: .8em 1em; margin: 1em 0; border-radius: 4px; }
.failure { background: #fde2e1; border: 2px solid #c0392b; }
.warning { background: #fff4d6; border: 2px solid #e0a800; }
.note { background: #eef3fb; border: 1px solid #7a9cd3; }
pre { background: #f7f7f7; padding: .6em; overflow-x: auto; font-size: .85em; }
img { max-width: 100%; border: 1px solid #ddd; margin: .5em 0; }
"""


@dataclass(frozen=True)
class FigureRef:
    """A PNG to embed, with its caption."""

    path: Path
    caption: str


def _us(value: Any) -> str:
    return "–" if value is None else f"{value / 1e3:,.1f}"


def _row(cells: Sequence[str], header: bool = False, classes: Sequence[str] = ()) -> str:
    tag = "th" if header else "td"
    out = []
    for i, cell in enumerate(cells):
        cls = ["name"] if i == 0 else []
        if i < len(classes) and classes[i]:
            cls.append(classes[i])
        attr = f' class="{" ".join(cls)}"' if cls else ""
        out.append(f"<{tag}{attr}>{cell}</{tag}>")
    return "<tr>" + "".join(out) + "</tr>"


# (label, how to read it from a task entry, whether a non-zero value is bad)
METRICS: tuple[tuple[str, Any, bool], ...] = (
    ("period [µs]", lambda t: _us(t.get("period_ns")), False),
    ("scheduling", lambda t: f"{t.get('policy', '?')}:{t.get('priority', '?')}", False),
    ("cpu", lambda t: "any" if t.get("cpu") is None else str(t["cpu"]), False),
    ("real-time", lambda t: "yes" if t.get("rt") else "<b>no</b>", False),
    ("cycles", lambda t: f"{t.get('cycles', 0):,}", False),
    ("left out (trimmed)", lambda t: str(t.get("trimmed", "–")), False),
    ("latency min [µs]", lambda t: _us(t.get("latency_ns", {}).get("min")), False),
    ("latency p50 [µs]", lambda t: _us(t.get("latency_ns", {}).get("p50")), False),
    ("latency p99 [µs]", lambda t: _us(t.get("latency_ns", {}).get("p99")), False),
    ("latency max [µs]", lambda t: _us(t.get("latency_ns", {}).get("max")), False),
    ("jitter min [µs]", lambda t: _us(t.get("period_jitter_ns", {}).get("min")), False),
    ("jitter p99 [µs]", lambda t: _us(t.get("period_jitter_ns", {}).get("p99")), False),
    ("jitter max [µs]", lambda t: _us(t.get("period_jitter_ns", {}).get("max")), False),
    ("exec p50 [µs]", lambda t: _us(t.get("exec_ns", {}).get("p50")), False),
    ("exec max [µs]", lambda t: _us(t.get("exec_ns", {}).get("max")), False),
    ("cycles beyond ±3 % of P", lambda t: str(t.get("jitter_over_3pct", "–")), False),
    ("deadline misses", lambda t: str(t.get("deadline_misses", "–")), True),
    ("overruns (skipped releases)", lambda t: str(t.get("overruns", "–")), True),
    # the two kinds, as summary.json names them (an older run's summary has "stale_reads" for the first)
    ("stale connection reads", lambda t: str(t.get("stale_connection_reads", t.get("stale_reads", "–"))), True),
    ("stale device reads", lambda t: str(t.get("stale_device_reads", "–")), True),
)


RUN_FACTS: tuple[tuple[str, Any], ...] = (
    ("mode", lambda r: r.summary.get("mode")),
    ("kernel", lambda r: (r.summary.get("machine") or {}).get("kernel")),
    ("preemption", lambda r: (r.summary.get("machine") or {}).get("preemption")),
    ("isolated cpus", lambda r: (r.summary.get("machine") or {}).get("isolated_cpus")),
    ("stopped by", lambda r: r.summary.get("stopped_by")),
    ("failure", lambda r: (r.failure or {}).get("reason", "none")),
)


CLOCK_METRICS = ("latency", "jitter", "exec", "cycles beyond")
"""Metrics a simulated clock makes 0 by construction: shown as – for a simulation."""


def _metric(run: Run, entry: dict[str, Any], label: str, read: Any) -> str:
    return "–" if run.simulated and label.startswith(CLOCK_METRICS) else read(entry)


def _bad(value: str, flag: bool) -> str:
    return "bad" if flag and value not in ("0", "–") else ""


def summary_table(run: Run) -> str:
    """One row per metric, one column per task (fits the page however many metrics there are)."""
    names = list(run.tasks)
    head = _row(["metric", *(escape(n) for n in names)], header=True)
    rows = [criterion_row(run, names)]
    for label, read, flag in METRICS:
        values = [_metric(run, run.tasks[n], label, read) for n in names]
        rows.append(_row([label, *values], classes=["", *(_bad(v, flag) for v in values)]))
    return f'<div class="scroll"><table>{head}{"".join(rows)}</table></div>'


def criterion(run: Run, task: str) -> tuple[str, str]:
    """The thesis's firm real-time requirement for one task: (verdict text, css class).

    Met when the largest period jitter is within ±3 % of P and at most 0.01 % of the
    periods missed their deadline (thesis, chapter 3). Not applicable to a simulation.
    """
    entry = run.tasks.get(task, {})
    if run.summary.get("mode") == "simulate":
        return "not applicable (simulated clock)", ""
    period_ns = entry.get("period_ns") or 0
    jitter = entry.get("period_jitter_ns") or {}
    low, high = jitter.get("min"), jitter.get("max")
    cycles = entry.get("cycles") or 0
    if not period_ns or low is None or high is None or not cycles:
        return "not enough cycles to judge", ""
    limit_ns = 0.03 * period_ns
    worst_ns = max(abs(low), abs(high))
    misses = entry.get("deadline_misses") or 0
    allowed = 1e-4 * cycles
    problems = []
    if worst_ns > limit_ns:
        problems.append(f"max |jitter| {worst_ns / 1e3:,.1f} µs &gt; {limit_ns / 1e3:g} µs "
                        f"({entry.get('jitter_over_3pct', '?')} cycles beyond)")
    if misses > allowed:
        problems.append(f"{counted(misses, 'deadline miss', 'deadline misses')} &gt; 0.01 % of {cycles:,} periods")
    if not problems:
        return (f"met: max |jitter| {worst_ns / 1e3:,.1f} µs ≤ {limit_ns / 1e3:g} µs, "
                f"{counted(misses, 'deadline miss', 'deadline misses')}"), "ok"
    return "not met: " + "; ".join(problems), "amber"


def criterion_row(run: Run, names: Sequence[str]) -> str:
    verdicts = [criterion(run, n) for n in names]
    cells = "".join(f'<td class="criterion {css}">{text}</td>' for text, css in verdicts)
    return ('<tr><td class="name criterion">thesis criterion: |jitter| ≤ 3 % of P, '
            f"misses ≤ 0.01 %</td>{cells}</tr>")


def comparison_table(runs: Sequence[Run]) -> str:
    """One column per run, one row per (task, metric): the runs side by side."""
    head = _row(["task / metric", *(escape(r.label) for r in runs)], header=True)
    rows = [f'<tr><th class="name" colspan="{len(runs) + 1}">run</th></tr>']
    for label, read in RUN_FACTS:
        rows.append(_row([label, *(escape(_plain(read(run))) for run in runs)]))
    tasks = list(dict.fromkeys(name for run in runs for name in run.tasks))
    for name in tasks:
        rows.append(f'<tr><th class="name" colspan="{len(runs) + 1}">{escape(name)}</th></tr>')
        verdicts = [criterion(run, name) if name in run.tasks else ("–", "") for run in runs]
        rows.append('<tr><td class="name criterion">thesis criterion</td>'
                    + "".join(f'<td class="criterion {css}">{text}</td>' for text, css in verdicts) + "</tr>")
        for label, read, flag in METRICS:
            values = [_metric(run, run.tasks[name], label, read) if name in run.tasks else "–" for run in runs]
            rows.append(_row([label, *values], classes=["", *(_bad(v, flag) for v in values)]))
    return f'<div class="scroll"><table>{head}{"".join(rows)}</table></div>'


def machine_table(run: Run) -> str:
    """Where and how the numbers were measured."""
    summary = run.summary
    machine = summary.get("machine") or {}
    facts = [
        ("app", summary.get("app")), ("mode", summary.get("mode")), ("started", summary.get("started")),
        ("duration [s]", _duration(summary)), ("stopped by", summary.get("stopped_by")),
        ("real-time capable", summary.get("rt_capable")),
        *((key.replace("_", " "), value) for key, value in machine.items()),
    ]
    rows = [_row([escape(str(k)), escape(_plain(v))]) for k, v in facts]
    return f"<table>{''.join(rows)}</table>"


def _duration(summary: dict[str, Any]) -> str:
    """How long the run ran; a run that ended before its duration (a failure, a stop) says both."""
    asked, elapsed = summary.get("duration_s"), summary.get("elapsed_s")
    if not isinstance(elapsed, int | float):  # a summary from before elapsed_s
        return _plain(asked)
    if summary.get("stopped_by") == "duration" and isinstance(asked, int | float):
        return f"{asked:g}"
    of = f" of the {asked:g} asked" if isinstance(asked, int | float) else " (until stopped)"
    return f"{elapsed:.3f}{of}, stopped by {summary.get('stopped_by')}"


def _plain(value: Any) -> str:
    if isinstance(value, list | tuple):
        return ", ".join(str(v) for v in value) or "none"
    return "–" if value is None else str(value)


def banners(run: Run) -> str:
    """Failure, non-real-time, simulation and data problems, most serious first."""
    out = []
    failure = run.failure
    if failure:
        where = ", ".join(f"{k} {failure[k]}" for k in ("task", "phase", "cycle") if failure.get(k) is not None)
        out.append(f'<div class="banner failure"><b>This run FAILED</b> ({escape(where)}): '
                   f'{escape(str(failure.get("reason", "")))}{_traceback(str(failure.get("traceback") or ""))}'
                   "The figures show the cycles recorded until then.</div>")
    non_rt = run.non_rt_tasks
    if non_rt:
        reasons = "; ".join(f"{escape(n)}: {escape(str(run.tasks[n].get('rt_reason') or 'no reason given'))}"
                            for n in non_rt)
        out.append(f'<div class="banner warning"><b>Not real-time:</b> task(s) {escape(", ".join(non_rt))} ran '
                   f"without a real-time scheduling policy ({reasons}). Their numbers show what an ordinary "
                   "Linux process gets, not what the machine can do under SCHED_FIFO (see <code>rtloop doctor"
                   "</code>).</div>")
    if run.simulated:
        out.append('<div class="banner note"><b>simulated: no timing</b> — an offline simulation (<code>rtloop '
                   "simulate</code>): the clock is simulated, so latency and jitter are zero by construction and "
                   f"no timing figures are drawn; only the signals are meaningful.{_host_exec(run)}</div>")
    for problem in run.problems:
        out.append(f'<div class="banner warning">{escape(problem)}</div>')
    return "".join(out)


def misses_list(run: Run) -> str:
    """Why cycles were late: one line per task, kind and cause (summary.json ``misses``; rtloop why)."""
    lines = (run.summary.get("misses") or {}).get("lines", [])
    if not lines:
        return ""
    items = "".join(f"<li>{escape(str(line))}</li>" for line in lines)
    return (f"<h3>Why cycles were late</h3><ul>{items}</ul><p>The evidence for one cycle: <code>rtloop why "
            f"{escape(str(run.path))} --cycle N</code>. The latency-over-time figure marks each miss.</p>")


def _traceback(text: str) -> str:
    """The failure's traceback, the user's own line first (Python lists it last, under rtloop's)."""
    if not text:
        return ""
    own = user_frames(text)
    first = (f"<p>In your code (innermost last):</p><pre>{escape(chr(10).join(own))}</pre>"
             "<p>The whole traceback:</p>") if own else ""
    return f"{first}<pre>{escape(text)}</pre>"


def _host_exec(run: Run) -> str:
    """What a simulation measured of time: each step's execution on the host (not real time)."""
    parts = [f"{escape(name)} mean {_us(entry['host_exec_ns'].get('mean'))} µs, max "
             f"{_us(entry['host_exec_ns'].get('max'))} µs"
             for name, entry in run.tasks.items() if isinstance(entry.get("host_exec_ns"), dict)]
    return f" Host execution time per step (not real time): {'; '.join(parts)}." if parts else ""


def image(fig: FigureRef) -> str:
    data = base64.b64encode(fig.path.read_bytes()).decode("ascii")
    return (f'<figure><img alt="{escape(fig.caption)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{escape(fig.caption)}</figcaption></figure>")


def page(runs: Sequence[Run], run_figures: dict[str, list[FigureRef]], comparison: list[FigureRef]) -> str:
    """The whole report as one HTML string."""
    title = "rtloop report — " + ", ".join(r.label for r in runs)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{escape(title)}</title>"
             f"<style>{STYLE}</style></head><body><h1>{escape(title)}</h1>"]
    parts.append("<p>Wake-up latency = start − release (as cyclictest). Period jitter = (start<sub>k</sub> − "
                 "start<sub>k−1</sub>) − P over consecutive cycles. Distributions leave out the first and last "
                 "cycles as recorded in <code>summary.json</code> (<code>trimmed</code>); counts of misses and "
                 "overruns use every cycle. The thesis's criterion: |jitter| ≤ 3 % of P.</p>")
    if len(runs) > 1:
        parts.append("<h2>Runs side by side</h2>")
        parts.extend(banners(r) and f"<h3>{escape(r.label)}</h3>{banners(r)}" for r in runs)
        parts.append(comparison_table(runs))
        parts.extend(image(f) for f in comparison)
    for run in runs:
        parts.append(f"<h2>Run {escape(run.label)} <small>({escape(str(run.path))})</small></h2>")
        parts.append(banners(run))
        parts.append("<h3>Summary</h3>" + summary_table(run) + misses_list(run))
        parts.append("<h3>Machine</h3>" + machine_table(run))
        parts.extend(image(f) for f in run_figures.get(run.label, []))
    parts.append("</body></html>")
    return "\n".join(parts)
