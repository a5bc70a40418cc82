"""JIWY on two EtherCAT drives: the task plans the pan/tilt trajectory, the drives follow it in CSP.

The drives close the position loop themselves (cyclic synchronous position): each is told where
its joint must be at each cycle. In the emulated drives (``rtloop io emulate ethercat --app``,
and the device's twin in ``rtloop simulate``) that loop is the thesis's PID
(``kp·(1 + τD·s)/(1 + β·τD·s)·(1 + 1/(τI·s))``, pan kp 0.3, τD 0.1 s; tilt kp 0.2, τD 0.2 s, β 0.1)
on JIWY's motor, gear, belt and camera inertia, expressed at the motor shaft (see the app file).
"""

from __future__ import annotations

from itertools import pairwise

from rtloop import Runnable
from rtloop.runnable import FloatVector

__all__ = ["Trajectory"]

# (time s, pan rad, tilt rad): the gimbal looks right and up, left and down, and back home
WAYPOINTS = ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (3.0, 0.5, 0.3), (5.0, -0.5, -0.2), (7.0, -0.5, -0.2),
             (9.0, 0.0, 0.0))


def minimum_jerk(s: float) -> float:
    """0 → 1 over s in [0, 1] with zero velocity and acceleration at both ends."""
    s = min(1.0, max(0.0, s))
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


class Trajectory(Runnable):
    """u = [pan_position_rad, tilt_position_rad] (measured) → y = [pan target, tilt target, pan error, tilt error]."""

    n_inputs = 2
    n_outputs = 4
    input_names = ("pan_measured_rad", "tilt_measured_rad")
    output_names = ("pan_target_rad", "tilt_target_rad", "pan_error_rad", "tilt_error_rad")

    def __init__(self, period_s: float = 0.001) -> None:
        self.period_s = period_s

    def step(self, u: FloatVector, y: FloatVector) -> None:
        t = self.tick.cycle * self.period_s
        pan = tilt = 0.0
        for (t0, pan0, tilt0), (t1, pan1, tilt1) in pairwise(WAYPOINTS):
            if t <= t1:
                s = minimum_jerk((t - t0) / (t1 - t0))
                pan, tilt = pan0 + (pan1 - pan0) * s, tilt0 + (tilt1 - tilt0) * s
                break
        else:
            pan, tilt = WAYPOINTS[-1][1], WAYPOINTS[-1][2]
        y[0] = pan
        y[1] = tilt
        y[2] = pan - u[0]
        y[3] = tilt - u[1]
