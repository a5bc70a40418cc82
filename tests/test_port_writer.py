"""A held writer of an input port (``RunningApp.writer``): its segment mapped once, however many
values it posts; each write checked as a one-off write is; several writers at once."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import unique_name  # type: ignore[import-not-found]
from rt_test_runnables import Gain  # type: ignore[import-not-found]
from rtloop.app.builder import App
from rtloop.errors import PortValueError
from rtloop.ipc.ports import RunningApp, connect_app
from rtloop.runtime.layout import AppLayout


def test_a_port_writer_maps_its_segment_once_and_posts_every_value(monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: every write to a port mapped and unmapped its segment (a bridge at 1 kHz: 1000 mmaps a second)."""
    app = App(unique_name("writer"))
    task = app.add_task("g", Gain(1), period_ns=1_000_000)
    app.port("setpoint", to=task.u[0], value_range=(-1.0, 1.0))
    layout = AppLayout.create(app)  # the segments and registry a live app makes; no task is started
    try:
        running = connect_app(app.name)
        opened: list[str] = []
        attach = RunningApp.segment
        monkeypatch.setattr(RunningApp, "segment", lambda self, name: opened.append(name) or attach(self, name))
        with running.writer("setpoint") as writer, running.writer("setpoint") as other:
            for i in range(200):
                writer.write([i / 200])
                assert writer.channel.peek().tolist() == [i / 200]
            other.write(np.array([-0.5]))  # writers share the port: no exclusive hold
            with pytest.raises(PortValueError, match=r"outside its range"):
                writer.write([7.0])
        assert len(opened) == 2  # one mapping per writer, not one per value
        monkeypatch.undo()
        assert running.peek("setpoint").tolist() == [-0.5]
        running.write("setpoint", [0.25])  # the one-off write is a writer opened for one value
        assert running.peek("setpoint").tolist() == [0.25]
    finally:
        layout.close()
