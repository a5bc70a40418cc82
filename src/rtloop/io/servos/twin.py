"""A servo bus's twin: the device's own code against the servo model, in process.

``rtloop simulate`` puts it in the device's place. It runs the very same driver (set-up, sync
write, sync read, conversions, checks) with its packets going to a :class:`~.model.BusModel`
through a function call instead of a serial line, so a run against the emulator (the same model
behind a pty, started with the app's period) equals the simulation bit for bit: both see the same
bytes. The servos start at rest at 2048 ticks, as ``rtloop emulate`` starts them by default.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rtloop.io.device import FloatVector
from rtloop.io.servos.line import ModelLine
from rtloop.io.servos.model import build_bus
from rtloop.runnable import Runnable


class ServoBusTwin(Runnable):
    """u = the device's commands → y = its readings, one sync write and one sync read per step."""

    def __init__(self, device_class: type, name: str, settings: dict[str, Any], n_inputs: int,
                 n_outputs: int) -> None:
        self.device_class, self.name, self.settings = device_class, name, dict(settings)
        self.n_inputs, self.n_outputs = n_inputs, n_outputs

    def prerun(self) -> None:
        device = self.device = self.device_class(self.name, **self.settings)
        period_s = self.tick.period_ns * 1e-9
        specs = device.specs
        self.bus = build_bus(device.protocol_name, [spec.servo_id for spec in specs],
                             [spec.model.name for spec in specs], period_s,
                             baud_rate=self.settings["baudrate"])
        # as a run: configure, the safe state held until T0, then activate
        device.attach(ModelLine(self.bus))
        device.write_safe(np.zeros(self.n_inputs))
        device.activate()

    def step(self, u: FloatVector, y: FloatVector) -> None:
        self.device.write(u)
        self.device.read(y)
