"""The runnables of the two-apps example: a sine sensor and a controller that watches it."""

from __future__ import annotations

import math

from rtloop import Runnable


class Sine(Runnable):
    """y = [amplitude · sin(2π f t), t]: a sensor reading and the sensor's own tick time t (s)."""

    n_inputs, n_outputs = 0, 2
    output_names = ("value", "t_s")

    def __init__(self, amplitude: float = 1.0, frequency_hz: float = 1.0) -> None:
        self.amplitude, self.frequency_hz = amplitude, frequency_hz

    def step(self, u, y) -> None:
        t = self.tick.time_s
        y[0] = self.amplitude * math.sin(2 * math.pi * self.frequency_hz * t)
        y[1] = t  # travels with the value: the two apps' clocks start at different times


class Monitor(Runnable):
    """u = [value, t_s] as last received; y = [value low-pass filtered, samples received so far].

    A stand-in for a real controller: it only sees the latest value the ROS 2 bridge
    wrote, once per tick, and counts how often a new one (a new ``t_s``) came in.
    """

    n_inputs, n_outputs = 2, 2
    input_names = ("value", "t_s")
    output_names = ("filtered", "samples")

    def __init__(self, time_constant_s: float = 0.05) -> None:
        self.time_constant_s = time_constant_s
        self.filtered = 0.0
        self.samples = 0
        self.last_t = 0.0

    def step(self, u, y) -> None:
        if u[1] != self.last_t:
            self.samples += 1
            self.last_t = u[1]
        alpha = self.tick.period_ns * 1e-9 / self.time_constant_s
        self.filtered += alpha * (u[0] - self.filtered)
        y[0] = self.filtered
        y[1] = self.samples
