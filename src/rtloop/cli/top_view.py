"""How ``rtloop top`` draws what :mod:`rtloop.toolbox.monitor` sees: one rich table per app."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

from rich import box
from rich.console import Console, Group, RenderableType
from rich.table import Table
from rich.text import Text

from rtloop.toolbox.monitor import LATENCY_MAX_NOTE, AppView, Monitor, TaskView, unreachable_notes

COLUMNS = ("task", "state", "PID", "CPU", "sched", "cycle", "cyc/s", "overruns", "misses", "stale conn",
           "lat now µs", "lat max µs", "exec µs", "%CPU", "invol cs", "minflt", "majflt", "GC")


def _num(value: float | int | None, fmt: str = "{:,}") -> str:
    return "n/a" if value is None else fmt.format(value)


# Columns dropped first when the terminal is narrow (most important last).
DROP_ORDER = ("GC", "majflt", "state", "cyc/s", "minflt", "PID", "invol cs", "stale conn", "CPU", "exec µs", "%CPU")


def _row_cells(t: TaskView) -> dict[str, str | Text]:
    bad = "bold red"
    return {
        "task": t.name, "state": Text(t.state, style="green" if t.state == "RUNNING" else "yellow"),
        "PID": str(t.pid), "CPU": t.cpu,
        "sched": Text(t.sched, style="" if t.sched.startswith(("fifo", "rr", "deadline")) else bad),
        "cycle": f"{t.cycles:,}", "cyc/s": _num(t.cycles_per_s, "{:,.0f}"),
        "overruns": Text(str(t.overruns), style=bad if t.overruns else ""),
        "misses": Text(str(t.deadline_misses), style=bad if t.deadline_misses else ""),
        "stale conn": Text(str(t.stale_reads), style=bad if t.stale_reads else ""),
        "lat now µs": f"{t.latency_now_ns / 1e3:,.1f}", "lat max µs": f"{t.latency_max_ns / 1e3:,.1f}",
        "exec µs": f"{t.exec_last_ns / 1e3:,.1f}", "%CPU": _num(t.cpu_percent, "{:.1f}"),
        "invol cs": _num(t.nonvoluntary_ctxt_switches), "minflt": _num(t.minflt),
        "majflt": Text(_num(t.majflt), style=bad if t.majflt else ""), "GC": t.gc_collections,
    }


def _fitting_columns(rows: list[dict[str, str | Text]], width: int) -> list[str]:
    """Every column if they fit in ``width``, else without the least important ones."""
    def needed(column: str) -> int:
        return max([len(column), *(len(str(row[column])) for row in rows)]) + 3

    columns = list(COLUMNS)
    for victim in DROP_ORDER:
        if sum(needed(c) for c in columns) + 1 <= width:
            break
        columns.remove(victim)
    return columns


def render(views: list[AppView], width: int = 250, unreachable: Sequence[str] = ()) -> RenderableType:
    """The frame: one table per app (columns that fit in ``width``) and the notes; ``unreachable``:
    a line per app that runs as another user (whom to run top as)."""
    others = [Text(line, style="yellow") for line in unreachable]
    if not views:
        return Group(*others) if others else Text("no running rtloop app found (looked for registries in /dev/shm)",
                                                  style="yellow")
    tables: list[RenderableType] = []
    for view in views:
        rows = [_row_cells(t) for t in view.tasks]
        columns = _fitting_columns(rows, width)
        table = Table(title=f"{view.app}  (supervisor pid {view.pid})", box=box.SQUARE, title_justify="left")
        for column in columns:
            table.add_column(column, justify="left" if column in ("task", "state", "CPU", "sched") else "right",
                             no_wrap=True)
        for row in rows:
            table.add_row(*(row[c] for c in columns))
        tables.append(table)
        if view.summary_line:
            tables.append(Text(view.summary_line))
    tables.extend(others)
    tables.append(Text(LATENCY_MAX_NOTE + ".\nGC: not readable from outside a task process (rtloop disables "
                       "collection in the loop). cycle: release index (skipped releases included).", style="dim"))
    return Group(*tables)


def frames(monitor: Monitor, interval_s: float, console: Console) -> Iterator[RenderableType]:
    """Endless frames, ``interval_s`` apart, polling in between; fitted to the console's current width."""
    while True:
        views = monitor.snapshot()
        yield render(views, console.width, unreachable_notes(monitor.refused))
        monitor.poll_for(interval_s)
