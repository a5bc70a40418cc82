"""One wheel's speed profile in CSV: the drive closes the velocity loop, the task says the speed.

A trapezoid: at rest for 0.5 s, up to 3 rad/s in 1 s, held, down through zero to -3 rad/s, held,
back to rest. The error (target minus measured) is an output, to plot the drive's following.
"""

from __future__ import annotations

from itertools import pairwise

from rtloop import Runnable
from rtloop.runnable import FloatVector

__all__ = ["SpeedProfile"]

# (time s, wheel speed rad/s): straight lines between these points
PROFILE = ((0.0, 0.0), (0.5, 0.0), (1.5, 3.0), (3.5, 3.0), (5.0, -3.0), (6.5, -3.0), (7.5, 0.0))


def speed_at(t_s: float) -> float:
    for (t0, v0), (t1, v1) in pairwise(PROFILE):
        if t0 <= t_s < t1:
            return v0 + (v1 - v0) * (t_s - t0) / (t1 - t0)
    return PROFILE[-1][1] if t_s >= PROFILE[-1][0] else PROFILE[0][1]


class SpeedProfile(Runnable):
    """u = [measured wheel speed rad/s] → y = [target wheel speed rad/s, error rad/s]."""

    n_inputs = 1
    n_outputs = 2
    input_names = ("measured_rad_s",)
    output_names = ("target_rad_s", "error_rad_s")

    def step(self, u: FloatVector, y: FloatVector) -> None:
        target = speed_at(self.tick.time_s)  # this release's time since T0 (k·P)
        y[0] = target
        y[1] = target - u[0]
