"""What a person watching a run sees while it goes: the console's progress and notices, and the
Foxglove live view.

The supervisor calls a :class:`RunView` at the run's stages (before anything starts, while the
tasks prepare, at T0, after every drain, on the way out); it shows the run and decides nothing
about it. The progress line itself is the caller's to draw (``on_progress``: the CLI's
``cli/run.py:show_progress``); a notice is one line on stderr unless the caller takes it.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rtloop.app.builder import App
from rtloop.ipc.status import StatusWord
from rtloop.linux import rt
from rtloop.runtime.session import RunSession


@dataclass(frozen=True, slots=True)
class Progress:
    """What the console shows while a run goes on (the CLI formats it)."""

    elapsed_s: float
    duration_s: float | None
    deadline_misses: int
    latency_now_ns: int
    recording_stopped: str
    lost: int
    """Timing records, signal rows and logged inputs lost so far (the supervisor fell behind)."""


class RunView:
    """The console's progress and notices and, if the app asks for it, the Foxglove live view."""

    def __init__(self, app: App, on_progress: Callable[[Progress], None] | None = None,
                 on_notice: Callable[[str], None] | None = None) -> None:
        self.app = app
        self.on_progress = on_progress
        self.on_notice = on_notice or print_notice
        self.live: Any = None  # the LiveView (record/foxglove_live.py), once open
        self.recording_stopped = ""  # the recorder's reason, once said
        self.lost_said = 0  # the records lost when that was last looked at (the first loss is said)

    def check(self) -> None:
        """Before anything starts: a live view asked for without foxglove-sdk installed stops the run."""
        if self.app.live_view is not None:
            from rtloop.record.foxglove_live import import_foxglove

            import_foxglove()

    def open_live_view(self, session: RunSession) -> None:
        """Start the Foxglove server if the app asks for one (in this non-real-time process)."""
        if self.app.live_view is None:
            return
        from rtloop.record.foxglove_live import LiveView

        recorder = session.recorder
        names = recorder.signals.names if recorder.signals is not None else []
        assert session.layout.registry_path is not None
        self.live = LiveView(self.app, self.app.live_view, names, session.layout.registry_path)
        recorder.live = self.live
        self.on_notice(f"Foxglove live view on {self.live.url} (Foxglove: Open connection → Foxglove WebSocket)"
                       f"{self.live.reach}")

    def start(self, t0_ns: int, wall_t0_ns: int) -> None:
        """At T0: the live view's clock starts."""
        if self.live is not None:
            self.live.start(t0_ns, wall_t0_ns)

    def after_drain(self, session: RunSession) -> None:
        """Say at once what went wrong with the recording: it stopped (and why), records are being lost."""
        recorder = session.recorder
        if recorder.stopped != self.recording_stopped:
            self.recording_stopped = recorder.stopped
            self.on_notice(self.recording_stopped)
        lost = session.losses.total()
        if lost > self.lost_said:
            if not self.lost_said:
                self.on_notice("the supervisor falls behind the recording: records are being lost "
                               "(counted in summary.json notes; signals.csv marks the gaps)")
            self.lost_said = lost

    def show_progress(self, session: RunSession, t0_ns: int, duration_s: float | None) -> None:
        """The progress line's figures, to the caller that draws it."""
        if self.on_progress is None:
            return
        tasks = session.layout.tasks.values()
        elapsed_s = max(0.0, (rt.now_ns() - t0_ns) / 1e9)
        if duration_s is not None:
            elapsed_s = min(elapsed_s, duration_s)
        self.on_progress(Progress(
            elapsed_s=elapsed_s, duration_s=duration_s,
            deadline_misses=sum(h.status[StatusWord.DEADLINE_MISSES] for h in tasks),
            latency_now_ns=max(h.status[StatusWord.LATENCY_LAST_NS] for h in tasks),
            recording_stopped=session.recorder.stopped, lost=session.losses.total(),
        ))

    def close(self) -> None:
        if self.live is not None:
            self.live.close()

    def summary(self) -> dict[str, Any]:
        """The live view's entry of summary.json ``bridges`` (empty without one)."""
        return self.live.summary() if self.live is not None else {}


def print_notice(text: str) -> None:
    sys.stderr.write(f"\nrtloop: {text}\n")
    sys.stderr.flush()
