"""JIWY's aim on two Dynamixel servos: the setpoints shaped into goal positions the servos can follow.

The servos close their own position loops; the real-time task decides where they go each
period: towards the setpoint at most ``speed_rad_s``, speeding up and slowing down at most
``accel_rad_s2`` (a trapezoidal profile), so a setpoint step becomes a smooth move.
u = [pan, tilt (measured, rad), pan, tilt setpoints (rad)] → y = [pan, tilt goals (rad)].
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from rtloop import Runnable


class AimPanTilt(Runnable):
    n_inputs, n_outputs = 4, 2
    input_names = ("pan_rad", "tilt_rad", "pan_setpoint_rad", "tilt_setpoint_rad")
    output_names = ("pan_goal_rad", "tilt_goal_rad")
    input_units = ("rad", "rad", "rad", "rad", "rad/s", "rad/s²")  # and of the parameters' inputs (the report's axes)
    output_units = ("rad", "rad")
    parameters: ClassVar[dict[str, float]] = {"speed_rad_s": 2.0, "accel_rad_s2": 20.0}

    def prerun(self) -> None:
        self.goal = np.zeros(2)
        self.speed = np.zeros(2)

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        dt = self.tick.period_ns * 1e-9
        for axis in range(2):
            left = u[2 + axis] - self.goal[axis]
            # the fastest speed from which the move still stops at the setpoint
            stoppable = math.sqrt(2.0 * self.accel_rad_s2 * abs(left))
            wanted = math.copysign(min(self.speed_rad_s, stoppable), left)
            change = max(-self.accel_rad_s2 * dt, min(self.accel_rad_s2 * dt, wanted - self.speed[axis]))
            self.speed[axis] += change
            step = self.speed[axis] * dt
            if abs(step) >= abs(left):  # arrived
                step, self.speed[axis] = left, 0.0
            self.goal[axis] += step
        y[:] = self.goal
