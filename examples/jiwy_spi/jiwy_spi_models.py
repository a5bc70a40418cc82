"""JIWY over SPI: the controller's side and the FPGA model (the SPI device's twin).

The controller is the PID pair of ``examples/jiwy``; it reads the encoders' positions (radians
at the camera, unwrapped from 16-bit counts by the frame layout) and writes a PWM duty per axis
and an enable bit. The FPGA model stands for the board the SPI frame goes to: PWM duty →
H-bridge (a steering of ``duty * STEERING_PER_DUTY``, none while not enabled) → motor and gearbox
(JIWY's plant) → encoder quantisation (the motor's angle in whole counts, 2000 a motor turn,
wrapped to 16 bits on the wire). It passes what it receives and what it answers through the
frame's own layouts (``FRAME_SEND`` and ``FRAME_RECEIVE``, the same tables as ``jiwy_spi.toml``),
so ``rtloop simulate`` sees the numbers the wire carries: duty rounded to 1/10000, positions in
whole counts. The example's README gives the protocol.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from rtloop import Runnable
from rtloop.io.bytelayout import ByteLayout, field_from_table
from rtloop.io.spiframe import frame_layout

# the models live in examples/jiwy; this example reuses them rather than copying them
_JIWY = str(Path(__file__).resolve().parent.parent / "jiwy")
if _JIWY not in sys.path:
    sys.path.append(_JIWY)

from jiwy_models import JiwyController, JiwyPlant  # noqa: E402

__all__ = ["FRAME_LENGTH", "FRAME_RECEIVE", "FRAME_SEND", "STEERING_PER_DUTY", "Controller", "FpgaModel", "Panel"]

STEERING_PER_DUTY = 4.0
"""The H-bridge: full duty drives the motor with a steering of 4 (JIWY's plant's unit)."""
ENABLED = 1.0
"""Status bit 0: the H-bridge is enabled."""

FRAME_LENGTH = 12
FRAME_SEND: list[dict[str, Any]] = [
    {"name": "pwm_pan", "start_byte": 1, "type": "i16", "duty": {"full_scale": 10000, "range": [-1.0, 1.0]}},
    {"name": "pwm_tilt", "start_byte": 3, "type": "i16", "duty": {"full_scale": 10000, "range": [-1.0, 1.0]}},
    {"name": "enable", "start_byte": 5, "type": "u8"},
]
FRAME_RECEIVE: list[dict[str, Any]] = [
    {"name": "encoder_pan", "start_byte": 1, "type": "u16", "encoder": {"counts_per_rev": 2000, "gear_ratio": 19}},
    {"name": "encoder_tilt", "start_byte": 3, "type": "u16", "encoder": {"counts_per_rev": 2000, "gear_ratio": 76}},
    {"name": "status", "start_byte": 5, "type": "u8"},
]


def frame_layouts() -> tuple[ByteLayout, ByteLayout]:
    """The frame's two directions, as the SPI device declares them (one layout each: a receive
    layout keeps its encoders' unwrapped counts)."""
    return (frame_layout([field_from_table(t, f"send[{i}]") for i, t in enumerate(FRAME_SEND)], FRAME_LENGTH, "send"),
            frame_layout([field_from_table(t, f"receive[{i}]") for i, t in enumerate(FRAME_RECEIVE)], FRAME_LENGTH,
                         "receive"))


class Controller(JiwyController):
    """u = [encoder_pan, encoder_tilt, status, SetPointPan, SetPointTilt] → y = [pwm_pan, pwm_tilt, enable]."""

    n_inputs = 5
    n_outputs = 3
    input_names = ("encoder_pan", "encoder_tilt", "status", "SetPointPan", "SetPointTilt")
    output_names = ("pwm_pan", "pwm_tilt", "enable")
    input_units = ("rad", "rad", "", "rad", "rad")
    output_units = ("", "", "")

    def __init__(self, step_size_s: float = 0.01) -> None:
        super().__init__(step_size_s)
        self._pid_u = np.zeros(4)
        self._pid_y = np.zeros(2)

    def _evaluate(self, u: Any, y: Any) -> None:
        pid_u, pid_y = self._pid_u, self._pid_y
        pid_u[0], pid_u[1], pid_u[2], pid_u[3] = u[0], u[1], u[3], u[4]
        super()._evaluate(pid_u, pid_y)
        y[0] = pid_y[0] / STEERING_PER_DUTY  # the frame's duty range clamps it to [-1, 1]
        y[1] = pid_y[1] / STEERING_PER_DUTY
        y[2] = 1.0  # enabled while the task runs; the safe state (PWM 0, enable 0) on every way out


class FpgaModel(JiwyPlant):
    """The FPGA and what it drives: u = [pwm_pan, pwm_tilt, enable] → y = [encoder_pan, encoder_tilt, status]."""

    n_inputs = 3
    n_outputs = 3
    input_names = ("pwm_pan", "pwm_tilt", "enable")
    output_names = ("encoder_pan", "encoder_tilt", "status")
    input_units = ("", "", "")
    output_units = ("rad", "rad", "")

    def __init__(self, step_size_s: float = 0.01) -> None:
        super().__init__(step_size_s)
        self.send, self.receive = frame_layouts()
        self._commands = np.zeros(3)
        self._steering = np.zeros(2)
        self._angles = np.zeros(3)
        self.enabled = False
        """Whether the H-bridge is enabled (the last command's enable bit), seen from the model's side."""
        self.duty = (0.0, 0.0)
        """The last duties received, seen from the model's side."""
        self.answer = bytearray(FRAME_LENGTH)
        """The answer of the last step as the wire carries it (its signals' bytes; the counter and the
        CRC are the server's, ``fpga_server.py``): what ``y`` was read from."""

    def _evaluate(self, u: Any, y: Any) -> None:
        commands = self._commands
        self.send.round_trip(u, commands)  # what the wire carried: duty in 1/10000, clamped to its range
        self.enabled = commands[2] >= 0.5
        self.duty = (commands[0], commands[1])
        steering = self._steering
        steering[0] = commands[0] * STEERING_PER_DUTY if self.enabled else 0.0
        steering[1] = commands[1] * STEERING_PER_DUTY if self.enabled else 0.0
        angles = self._angles
        super()._evaluate(steering, angles)
        angles[2] = ENABLED if self.enabled else 0.0
        # whole encoder counts, wrapped on the wire and unwrapped (the layout's round trip, through
        # the frame the FPGA answers with, so a server sends the very bytes y was read from)
        self.receive.pack_into(self.answer, 0, angles)
        self.receive.unpack_from(self.answer, 0, y)


class Panel(Runnable):
    """The GPIO panel's twin (the scope pin and the E-stop): no signals to carry."""

    n_inputs = 0
    n_outputs = 0

    def step(self, u: Any, y: Any) -> None:
        pass
