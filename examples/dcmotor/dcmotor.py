"""A DC motor and a PI speed controller: the example of a first week with rtloop.

Two tasks, each running every millisecond::

    setpoint_rad_s ──► PiSpeed ──voltage_V──► DcMotor ──► speed_rad_s, current_A
                         ▲                                    │
                         └──────────── speed_rad_s ───────────┘

:class:`DcMotor` is the plant, a plain-Python model; :class:`PiSpeed` is the controller,
a plain :class:`~rtloop.Runnable` whose gains are *live parameters*: set them in the app
file, or change them while the app runs (``rtloop port write dcmotor gains 0.08 4.0``).
"""

from __future__ import annotations

from rtloop import Runnable
from rtloop.models.python import PythonModel

SUPPLY_V = 24.0
"""The motor driver's supply: the controller never asks for more than ±24 V."""


class DcMotor(PythonModel):
    """A small 24 V brushed DC motor with an inertia on its shaft.

    u = [voltage_V, load_torque_Nm] → y = [speed_rad_s, current_A]::

        L·di/dt = V − R·i − ke·ω          (armature circuit)
        J·dω/dt = kt·i − b·ω − τ_load     (shaft)

    With these numbers: no-load speed about 480 rad/s (4600 rpm) at 24 V, stall current
    12 A, mechanical time constant J·R/(kt·ke) = 16 ms, electrical L/R = 0.5 ms. The
    electrical one is shorter than the 1 ms tick, so each tick integrates in 10 Euler
    substeps of 0.1 ms (one Euler step of 1 ms would be unstable).
    """

    n_inputs, n_outputs = 2, 2
    input_names = ("voltage_V", "load_torque_Nm")
    output_names = ("speed_rad_s", "current_A")
    input_units = ("V", "N·m")
    output_units = ("rad/s", "A")
    step_size_s = 0.001
    parameters = {  # noqa: RUF012 — PythonModel's parameters: set in the app file before the run
        "resistance_ohm": 2.0,
        "inductance_H": 1.0e-3,
        "torque_constant_Nm_per_A": 0.05,  # kt; in SI units equal to the back-EMF constant ke [V·s/rad]
        "inertia_kg_m2": 2.0e-5,
        "friction_Nm_s_per_rad": 1.0e-5,
    }
    SUBSTEPS = 10

    def initialize(self, u, y, t_s: float) -> None:
        self.speed_rad_s, self.current_A = 0.0, 0.0  # the motor starts at rest
        y[0], y[1] = self.speed_rad_s, self.current_A

    def calculate(self, u, y) -> None:
        p = self.parameters
        r, inductance, k = p["resistance_ohm"], p["inductance_H"], p["torque_constant_Nm_per_A"]
        inertia, friction = p["inertia_kg_m2"], p["friction_Nm_s_per_rad"]
        voltage, load = float(u[0]), float(u[1])  # Python floats: a division by zero raises, never a silent NaN
        dt = self.step_size_s / self.SUBSTEPS
        speed, current = self.speed_rad_s, self.current_A
        for _ in range(self.SUBSTEPS):
            di = (voltage - r * current - k * speed) / inductance
            dspeed = (k * current - friction * speed - load) / inertia
            current += dt * di
            speed += dt * dspeed
        self.speed_rad_s, self.current_A = speed, current
        y[0], y[1] = speed, current


class PiSpeed(Runnable):
    """PI speed controller with anti-windup, output limited to the supply.

    u = [speed_rad_s, setpoint_rad_s] → y = [voltage_V]

    The gains are live parameters (one line, below): ``self.kp`` is in V per rad/s,
    ``self.ki`` in V per rad. Chosen so that ki/kp cancels the motor's 16 ms time
    constant and the loop crosses over at about 60 rad/s: a step to 150 rad/s settles
    in about 50 ms, with a peak current near 5 A.
    """

    n_inputs, n_outputs = 2, 1
    input_names = ("speed_rad_s", "setpoint_rad_s")
    output_names = ("voltage_V",)
    input_units = ("rad/s", "rad/s", "V·s/rad", "V/rad")  # and of the parameters' inputs kp, ki
    output_units = ("V",)
    parameters = {"kp": 0.05, "ki": 3.0}  # noqa: RUF012 — live: the app file or `rtloop port write` changes them

    def prerun(self) -> None:
        self.integral_V = 0.0  # the integral term, in volts

    def step(self, u, y) -> None:
        error = float(u[1]) - float(u[0])
        period_s = self.tick.period_ns * 1e-9
        integral = self.integral_V + self.ki * error * period_s
        voltage = self.kp * error + integral
        if -SUPPLY_V < voltage < SUPPLY_V:
            self.integral_V = integral  # anti-windup: integrate only while the output is not limited
        y[0] = min(max(voltage, -SUPPLY_V), SUPPLY_V)
