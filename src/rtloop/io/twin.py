"""A twin in a device's place: the model that answers as the hardware does.

``rtloop simulate`` runs an app with every device replaced by its twin (a
:class:`~rtloop.Runnable` whose inputs are the device's commands and whose outputs are its
readings). The twin goes through the same :class:`~rtloop.io.host.TaskDevices` as the
device, so commands are guarded and timed exactly as in a real run; a twin's ``step`` is one
exchange with the device: it takes the commands written last and answers the readings.

A device whose safe write is itself an exchange (``Device.safe_write_is_exchange``: a serial
request, an SPI transfer) moves its state on at configure, before T0, and on the way out; the
twin steps on the safe values then too, so it sees every exchange the device sees.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rtloop.errors import DeviceFault
from rtloop.io.device import Device, FloatVector
from rtloop.runnable import Runnable


class TwinDevice(Device):
    """Stands in for ``name``: ``write`` keeps the commands, ``read`` steps the twin once."""

    kind = "twin"

    def __init__(self, name: str, twin: Runnable, like: Device, safe: Sequence[float] | FloatVector) -> None:
        super().__init__(name)
        self.twin = twin
        self.n_inputs, self.n_outputs = like.n_inputs, like.n_outputs
        self.input_names, self.output_names = like.input_names, like.output_names
        self.commands = np.array(safe, dtype=np.float64)  # the device's state before any write
        self.steps_on_safe_values = like.safe_write_is_exchange
        self.safe_answer = np.zeros(like.n_outputs)  # what the device answers to the safe values (read by nothing)

    def configure(self) -> None:
        self.twin.prerun()

    def read(self, y: FloatVector) -> None:
        self.twin.step(self.commands, y)

    def write(self, u: FloatVector) -> None:
        self.commands[:] = u

    def write_safe(self, u: FloatVector) -> None:
        """The safe values; one exchange with the twin where the device answers them (configure's
        included: the device's model moved on then, before T0, and so must the twin's)."""
        self.commands[:] = u
        if self.steps_on_safe_values and not isinstance(self.twin, PlaybackTwin):
            self.twin.step(self.commands, self.safe_answer)

    def close(self) -> None:
        self.twin.postrun()


class PlaybackTwin(Runnable):
    """What a device read in a real run, played back by cycle: ``rtloop replay`` puts it in the
    device's place, so a hardware run replays offline without the hardware. (The answers to safe
    values are not played back: no task read them.)"""

    def __init__(self, name: str, n_inputs: int, n_outputs: int, readings: dict[int, FloatVector]) -> None:
        self.name, self.n_inputs, self.n_outputs = name, n_inputs, n_outputs
        self.readings = readings
        """Cycle → the device's ``y`` as the task took it (elements no connection uses stay 0)."""

    def step(self, u: FloatVector, y: FloatVector) -> None:
        row = self.readings.get(self.tick.cycle)
        if row is None:
            raise DeviceFault(f"device {self.name!r}: the run logged no reading at cycle {self.tick.cycle}")
        y[:] = row
