"""JIWY's controller and plant for the CAN example: the models of ``examples/jiwy``, unchanged.

The controller runs as the real-time task; the plant runs twice over: in ``plant_node.py`` (a
separate process standing in for the gimbal's drive electronics on the CAN bus) and as the CAN
device's twin in ``rtloop simulate``. Both step it once per command exchange, so a run that
misses no deadline equals the simulation bit for bit.
"""

from __future__ import annotations

import sys
from pathlib import Path

# the models live in examples/jiwy; this example reuses them rather than copying them
_JIWY = str(Path(__file__).resolve().parent.parent / "jiwy")
if _JIWY not in sys.path:
    sys.path.append(_JIWY)

from jiwy_models import JiwyController, JiwyPlant  # noqa: E402

__all__ = ["Controller", "Plant"]


class Controller(JiwyController):
    """JIWY's PID pair: u = [MeasuredPan, MeasuredTilt, SetPointPan, SetPointTilt] → y = steering."""


class Plant(JiwyPlant):
    """JIWY's gimbal: u = [SteeringPan, SteeringTilt] → y = [AnglePan, AngleTilt] [rad]."""
