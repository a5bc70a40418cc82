"""An SO-100 style arm (six Feetech STS3215) holding a pose, then following a joint trajectory.

For ``hold_s`` the arm holds its rest pose; then every joint follows a smooth periodic path
around it (a sum of two sines per joint, each starting at zero speed and position offset, so
the move starts without a jump): the kind of reference a learned policy or a teleoperation
leader would stream, here computed at the task's period (500 Hz in the example).
u = the six measured joint positions (rad) → y = the six goal positions (rad), then the
largest tracking error over the joints (rad), for the record.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from rtloop import Runnable

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
REST_RAD = (0.0, -0.4, 0.6, 0.3, 0.0, 0.1)
AMPLITUDE_RAD = (0.6, 0.3, 0.4, 0.5, 0.8, 0.3)
PERIOD_S = (4.0, 3.0, 3.0, 2.0, 2.5, 1.5)


class PoseThenTrajectory(Runnable):
    n_inputs, n_outputs = 6, 7
    input_names = tuple(f"{joint}_rad" for joint in JOINTS)
    output_names = (*(f"{joint}_goal_rad" for joint in JOINTS), "largest_error_rad")
    input_units = ("rad",) * 6 + ("s", "")  # and of the parameters' inputs: hold_s, scale (a factor)
    output_units = ("rad",) * 7
    parameters: ClassVar[dict[str, float]] = {"hold_s": 0.5, "scale": 1.0}

    def prerun(self) -> None:
        self.rest = np.array(REST_RAD)
        self.amplitude = np.array(AMPLITUDE_RAD)
        self.omega = np.array([2 * math.pi / period for period in PERIOD_S])
        self.phase = np.zeros(6)
        self.goal = np.zeros(6)
        self.error = np.zeros(6)
        self.initial_outputs = np.array([*REST_RAD, 0.0])

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        t_s = self.tick.time_s - self.hold_s
        goal = self.goal
        if t_s <= 0.0:
            goal[:] = self.rest
        else:
            # 1 - cos starts at zero speed; the second sine at twice the rate adds a reversal
            np.multiply(self.omega, t_s, out=self.phase)
            np.cos(self.phase, out=goal)
            np.subtract(1.0, goal, out=goal)
            np.multiply(goal, self.amplitude * (0.5 * self.scale), out=goal)
            np.add(goal, self.rest, out=goal)
        np.subtract(u[:6], goal, out=self.error)
        y[:6] = goal
        y[6] = float(np.max(np.abs(self.error)))
