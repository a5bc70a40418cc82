"""The safe transition of a drive device (EtherCAT and CANopen), on every way a run ends: quick
stop while a drive is enabled (it brakes on its own ramp), disable voltage once at rest, exchange
after exchange outside the loop; then the device takes its drives off the bus's process data
(EtherCAT: SAFE-OP; CANopen: NMT pre-operational). One that does not finish within
``quick_stop_timeout_s`` (its frames lost, a cable pulled; a drive that does not follow) is a
fault naming the drives not seen stopped and the exchanges that did not come back: the run's notes
then say the drives are not known to be stopped, where before the transition returned as if they
were.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from rtloop.errors import DeviceFault
from rtloop.io.drives.cycle import DriveCycle

__all__ = ["SAFE_STEP_S", "safe_transition"]

SAFE_STEP_S = 0.001
"""The pace of the exchanges of the safe transition (outside the loop)."""


def safe_transition(cycle: DriveCycle, exchange: Callable[[], bool], n_readings: int, timeout_s: float,
                    unanswered: str, then: str) -> str:
    """Exchange the safe transition's outputs until every drive is stopped or ``timeout_s`` has
    passed (``exchange``: send them, True when the drives' answer is in the cycle's inputs; an
    OSError or DeviceFault when it cannot be sent): "" when they are, else what is wrong, naming
    ``unanswered`` ("frames not back within 800 µs") and what the caller does next, ``then`` (it
    raises it as a fault after doing so)."""
    deadline = time.monotonic() + timeout_s
    scratch = np.zeros(n_readings)  # the drives' readings are taken (their states), not reported
    done, sent, lost, failed = False, 0, 0, ""
    while time.monotonic() < deadline:
        done = cycle.safe_outputs()
        try:
            sent += 1
            if exchange():
                cycle.take_inputs(scratch, check=False)
            else:
                lost += 1
        except (OSError, DeviceFault) as error:
            failed = f"; the exchange could not be sent: {getattr(error, 'strerror', None) or error}"
            break
        if done:
            break
        time.sleep(SAFE_STEP_S)
    stopping = "" if done else cycle.still_stopping()  # (the last answer may show them stopped)
    if not stopping:
        return ""
    return (f"the safe transition did not finish within {timeout_s:g} s (quick_stop_timeout_s): {stopping}; {lost} "
            f"of {sent} {unanswered}{failed}; {then}")
