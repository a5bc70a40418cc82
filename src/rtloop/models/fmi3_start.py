"""Starting an FMI 3 co-simulation FMU with Event Mode when it takes it, without when it refuses it.

``hasEventMode="true"`` says an FMU *can* use Event Mode; whether it is used is the importer's
choice (FMI 3.0, ``fmi3InstantiateCoSimulation``'s ``eventModeUsed``): without it, the FMU
handles its events inside ``fmi3DoStep``. Some FMUs declare it and refuse it at instantiate
("Event Mode is not supported"); FMPy runs them without it, and so does rtloop, saying so.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any


def instantiate(fmu: Any, event_mode: bool, log: Callable[[int, bytes | None, bytes | None], None]) -> bool:
    """Instantiate ``fmu`` (an FMPy ``FMU3Slave``) with Event Mode if ``event_mode``, else, or when it
    refuses it, without; returns whether Event Mode is used. A refusal without Event Mode raises."""
    def attempt(used: bool) -> None:
        fmu.instantiate(eventModeUsed=used, earlyReturnAllowed=False,
                        logMessage=lambda _env, status, category, message: log(status, category, message))

    try:
        attempt(event_mode)
        return event_mode
    except Exception:
        if not event_mode:
            raise
    attempt(False)
    return False


def said(messages: Sequence[str]) -> str:
    """``; the FMU said: …`` (its last log message), or '' when it said nothing."""
    return f"; the FMU said: {messages[-1]}" if messages else ""
