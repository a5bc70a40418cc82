"""The safe transition of an EtherCAT drive device, on every way a run ends: quick stop while a
drive is enabled (it brakes on its own ramp), disable voltage once at rest, exchange after exchange
outside the loop; then the device asks for SAFE-OP. One that does not finish within
``quick_stop_timeout_s`` (its frames lost, a cable pulled; a drive that does not follow) is a
fault naming the drives not seen stopped and the frames that did not come back: the run's notes
say the drives are not known to be stopped, where before the transition returned as if they were.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from rtloop.io.drives.cycle import DriveCycle

__all__ = ["SAFE_STEP_S", "safe_transition"]

SAFE_STEP_S = 0.001
"""The pace of the exchanges of the safe transition (outside the loop)."""


def safe_transition(cycle: DriveCycle, exchange: Callable[[], int], n_readings: int, timeout_s: float,
                    timeout_us: float) -> str:
    """Exchange the safe transition's outputs (``exchange``: send the frame, the answer's working
    counter or -1 when it did not come back within ``timeout_us``) until every drive is stopped or
    ``timeout_s`` has passed: "" when they are, else what is wrong (the caller asks for SAFE-OP,
    then raises it as a fault)."""
    deadline = time.monotonic() + timeout_s
    scratch = np.zeros(n_readings)  # the drives' readings are taken (their states), not reported
    done, sent, lost, failed = False, 0, 0, ""
    while time.monotonic() < deadline:
        done = cycle.safe_outputs()
        try:
            sent += 1
            if exchange() >= 0:
                cycle.take_inputs(scratch, check=False)
            else:
                lost += 1
        except OSError as error:
            failed = f"; the frame could not be sent: {error.strerror or error}"
            break
        if done:
            break
        time.sleep(SAFE_STEP_S)
    stopping = "" if done else cycle.still_stopping()  # (the last answer may show them stopped)
    if not stopping:
        return ""
    return (f"the safe transition did not finish within {timeout_s:g} s (quick_stop_timeout_s): {stopping}; {lost} "
            f"of {sent} frames not back within {timeout_us:.0f} µs{failed}; SAFE-OP asked for: each slave's SM "
            "watchdog stops its drive when the frames stop")

