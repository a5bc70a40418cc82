"""A servo bus on a line that answers every sync read at once with the same bytes: no pty, no other
process and no model in the loop, so what is timed (``benchmarks/bench_servos.py``, its host share) or
counted by tracemalloc (``test_servo_checks.py``) is the device's own work."""

from __future__ import annotations

from typing import Any

from rtloop.io.device import build_device
from rtloop.io.servos.line import ModelLine
from rtloop.io.servos.model import build_bus


class AnswersAtOnce:
    """A line whose servos answer each sync read with ``answers``, at once; what is sent goes nowhere."""

    def __init__(self, answers: bytes) -> None:
        self.answers = answers

    def send(self, data: Any) -> None:
        pass

    def receive(self, buffer: memoryview, timeout_ns: int) -> int:
        buffer[:len(self.answers)] = self.answers
        return len(self.answers)

    def flush_input(self) -> None:
        pass


def servos_answering_at_once(kind: str, name: str, servos: list[dict[str, Any]]) -> Any:
    """A ``kind`` bus device of ``servos`` (their ``id`` and ``model``), set up against the bus model in
    process, then switched to a line that hands back the model's answers to its sync read at once."""
    ids = [servo["id"] for servo in servos]
    device = build_device(kind, name, {"port": "/dev/null", "servos": servos}, "app.toml")
    bus = build_bus(kind, ids, [servo["model"] for servo in servos], 0.002)
    device.attach(ModelLine(bus))
    device.activate()
    device.line = AnswersAtOnce(bytes(bus.receive(bytes(device.state.request))))
    return device
