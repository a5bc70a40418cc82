"""JIWY, the thesis's 2-DOF pan/tilt camera gimbal, as plain-Python models.

:class:`JiwyPlant` (2 in / 2 out) and :class:`JiwyController` (4 in / 2 out) follow the
order of evaluation of 20-sim generated code with the Euler method, step 1 ms, so they
match a 20-sim build of the same equations to rounding error. Use them directly as a
task's runnable: ``runnable = "jiwy_models:JiwyPlant"``.

Plant, per axis (motor momentum ``p`` [N·m·s] on the motor side of gear ``g`` and belt
``b``, camera angle ``theta`` [rad])::

    Jeq = Jmot + (g·b)²·Jcam             (camera inertia reflected to the motor)
    omega = p / Jeq                      motor speed [rad/s]
    omega_cam = g·b·omega                camera speed [rad/s]
    dp = r·u − Dmot·omega − g·b·(Dcam·omega_cam)
    dtheta = omega_cam,   y = theta

Controller, per axis, 20-sim's PID ``kp·(1 + τD·s)/(1 + β·τD·s)·(1 + 1/(τI·s))``::

    e = setpoint − measured
    pdout = pdstate + kp·e/β
    dpdstate = (kp·e − pdout)/(β·τD),  dpistate = pdout/τI
    y = pistate + pdout
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

from rtloop.models.python import PythonModel
from rtloop.runnable import FloatVector

__all__ = [
    "PAN_AXIS",
    "PAN_PID",
    "TILT_AXIS",
    "TILT_PID",
    "AxisParameters",
    "JiwyController",
    "JiwyPlant",
    "PidParameters",
]

STEP_SIZE_S = 0.001


@dataclass(frozen=True)
class AxisParameters:
    """One gimbal axis: motor, gear and belt, camera side."""

    r: float
    """Motor constant [N·m per unit of steering]."""
    j_mot: float
    """Motor inertia [kg·m²]."""
    d_mot: float
    """Motor damping [N·m·s/rad]."""
    g: float
    """Gear ratio."""
    b: float
    """Belt ratio."""
    j_cam: float
    """Camera-side inertia [kg·m²]."""
    d_cam: float
    """Camera-side damping [N·m·s/rad]."""


@dataclass(frozen=True)
class PidParameters:
    """20-sim PID: ``kp·(1 + τD·s)/(1 + β·τD·s)·(1 + 1/(τI·s))``."""

    kp: float
    tau_d_s: float
    beta: float
    tau_i_s: float


PAN_AXIS = AxisParameters(r=0.018, j_mot=2.06e-7, d_mot=1.77e-6, g=1 / 19, b=1.0,
                          j_cam=3e-4, d_cam=2e-4)
TILT_AXIS = AxisParameters(r=0.00701, j_mot=5.28e-8, d_mot=4e-7, g=1 / 19, b=0.25,
                           j_cam=4.5e-5, d_cam=1e-4)
PAN_PID = PidParameters(kp=0.3, tau_d_s=0.1, beta=0.1, tau_i_s=1000.0)
TILT_PID = PidParameters(kp=0.2, tau_d_s=0.2, beta=0.1, tau_i_s=1000.0)


class _TwoAxisEulerModel(PythonModel):
    """Two axes of two states each, integrated with Euler in 20-sim's order of evaluation.

    Subclasses give ``_evaluate(u, y)``: the outputs and the state rates from the current
    states and inputs.
    """

    def __init__(self, step_size_s: float, pan: object, tilt: object) -> None:
        super().__init__()
        self.step_size_s = step_size_s
        self.pan = pan
        self.tilt = tilt
        self.time_s = 0.0
        self.states = [0.0, 0.0, 0.0, 0.0]
        self.rates = [0.0, 0.0, 0.0, 0.0]

    def initialize(self, u: FloatVector, y: FloatVector, t_s: float) -> None:
        """Zero states at ``t_s``; outputs and rates from them and ``u`` (20-sim ``Initialize``)."""
        self.time_s = t_s
        self.states = [0.0, 0.0, 0.0, 0.0]
        self._evaluate(u, y)

    def calculate(self, u: FloatVector, y: FloatVector) -> None:
        """One Euler step: integrate with the previous rates, then evaluate with ``u``."""
        s = self.states
        r = self.rates
        h = self.step_size_s
        s[0] += h * r[0]
        s[1] += h * r[1]
        s[2] += h * r[2]
        s[3] += h * r[3]
        self.time_s += h
        self._evaluate(u, y)

    def _evaluate(self, u: FloatVector, y: FloatVector) -> None:
        raise NotImplementedError


class JiwyPlant(_TwoAxisEulerModel):
    """JIWY plant: u = [SteeringPan, SteeringTilt] → y = [AnglePan, AngleTilt] [rad].

    States [p_pan, theta_pan, p_tilt, theta_tilt]: motor momentum and camera angle per axis.
    """

    n_inputs = 2
    n_outputs = 2
    input_names = ("SteeringPan", "SteeringTilt")
    output_names = ("AnglePan", "AngleTilt")
    input_units = ("", "")  # steering: a motor command without a physical unit
    output_units = ("rad", "rad")
    pan: AxisParameters
    tilt: AxisParameters

    def __init__(
        self,
        step_size_s: float = STEP_SIZE_S,
        pan: AxisParameters = PAN_AXIS,
        tilt: AxisParameters = TILT_AXIS,
    ) -> None:
        super().__init__(step_size_s, pan, tilt)

    def _evaluate(self, u: FloatVector, y: FloatVector) -> None:
        s = self.states
        r = self.rates
        r[0], r[1] = _axis_rates(self.pan, s[0], float(u[0]))
        r[2], r[3] = _axis_rates(self.tilt, s[2], float(u[1]))
        y[0] = s[1]
        y[1] = s[3]


def _axis_rates(a: AxisParameters, p: float, u: float) -> tuple[float, float]:
    """(dp, dtheta) of one axis; the same expressions, in the same order, as the C fixtures."""
    gb = a.g * a.b
    j_eq = a.j_mot + gb * gb * a.j_cam
    omega = p / j_eq
    omega_cam = gb * omega
    tau_cam = a.d_cam * omega_cam
    return a.r * u - a.d_mot * omega - gb * tau_cam, omega_cam


class JiwyController(_TwoAxisEulerModel):
    """JIWY PID controller, one per axis.

    u = [MeasuredPan, MeasuredTilt, SetPointPan, SetPointTilt] → y = [SteeringPan, SteeringTilt].
    Direct feed-through: the output answers the current input at once.
    States [pdstate_pan, pistate_pan, pdstate_tilt, pistate_tilt].
    """

    n_inputs = 4
    n_outputs = 2
    input_names = ("MeasuredPan", "MeasuredTilt", "SetPointPan", "SetPointTilt")
    output_names = ("SteeringPan", "SteeringTilt")
    input_units = ("rad", "rad", "rad", "rad")
    output_units = ("", "")
    parameters: ClassVar[dict[str, float]] = {"kp_pan": PAN_PID.kp, "kp_tilt": TILT_PID.kp}
    """Proportional gains, settable by name (``parameters = { kp_pan = 0.4 }``, ``rtloop sweep``)."""
    pan: PidParameters
    tilt: PidParameters

    def __init__(
        self,
        step_size_s: float = STEP_SIZE_S,
        pan: PidParameters = PAN_PID,
        tilt: PidParameters = TILT_PID,
    ) -> None:
        super().__init__(step_size_s, pan, tilt)
        self.parameters.update(kp_pan=pan.kp, kp_tilt=tilt.kp)

    def set_parameters(self, values: dict[str, float]) -> None:
        super().set_parameters(values)
        self.pan = dataclasses.replace(self.pan, kp=self.parameters["kp_pan"])
        self.tilt = dataclasses.replace(self.tilt, kp=self.parameters["kp_tilt"])

    def take_over(self, u: FloatVector, y_last: FloatVector) -> None:
        """Bumpless transfer (``rtloop switch``): the first output equals ``y_last``, the outgoing
        controller's last one, on this release's inputs.

        The difference goes into the lead filter's state, not the integrator's: with τI = 1000 s
        the integrator would hold it for ever (a steady offset in the steering, so in the angle),
        while the lead filter lets it go within β·τD (20 ms for pan). The textbook PI puts it in
        the integrator, because there the integrator holds the steady state."""
        s = self.states
        values = u.tolist()
        for axis, (c, pd, pi) in enumerate(((self.pan, 0, 1), (self.tilt, 2, 3))):
            error = values[2 + axis] - values[axis]
            s[pd] = float(y_last[axis]) - s[pi] - c.kp * error / c.beta
        self.rates = [0.0, 0.0, 0.0, 0.0]  # the first step integrates nothing before it evaluates

    def _evaluate(self, u: FloatVector, y: FloatVector) -> None:
        s = self.states
        r = self.rates
        values = u.tolist()
        y[0], r[0], r[1] = _pid(self.pan, s[0], s[1], values[2] - values[0])
        y[1], r[2], r[3] = _pid(self.tilt, s[2], s[3], values[3] - values[1])


def _pid(c: PidParameters, pdstate: float, pistate: float, e: float) -> tuple[float, float, float]:
    """(output, dpdstate, dpistate) of one axis; same expressions as the C fixtures."""
    pdout = pdstate + c.kp * e / c.beta
    return pistate + pdout, (c.kp * e - pdout) / (c.beta * c.tau_d_s), pdout / c.tau_i_s
