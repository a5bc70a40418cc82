"""A device driver for the tests: it mirrors its commands into its readings (as ros2_control's
mock GenericSystem does) and logs every lifecycle call and write to a file, so a test can read,
after the run, what reached the "wire" and in which order. Importable by spawned task processes."""

from __future__ import annotations

import errno
import math
import os
import socket
import time
from typing import Any, ClassVar

import numpy as np

from rtloop import Runnable
from rtloop.errors import DeviceError
from rtloop.io.can import CanDevice
from rtloop.io.device import Device, Setting
from rtloop.io.gpio import EmergencyStop


def _positive(value: int) -> str | None:
    return None if value >= 0 else "must be ≥ 0"


class LogDevice(Device):
    kind = "test_log"
    settings: ClassVar[dict[str, Setting]] = {
        "log": Setting(str, doc="file every call is logged to"),
        "n_commands": Setting(int, 1, "commands it writes", check=_positive),
        "n_readings": Setting(int, 1, "readings it reads", check=_positive),
        "gain": Setting(float, 1.0, "reading = gain × last command"),
        "fail_in": Setting(str, "", "lifecycle call that raises (configure, activate, read, write)"),
        "nan_reading_at": Setting(float, -1.0, "its reading is NaN once the command has reached this (-1: never)"),
    }

    def __init__(self, name: str, **settings: Any) -> None:
        super().__init__(name, **settings)
        self.n_inputs, self.n_outputs = settings["n_commands"], settings["n_readings"]
        self.input_names = tuple(f"c{i}" for i in range(self.n_inputs))
        self.fd = -1
        self.last = np.zeros(self.n_inputs)

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "fd": -1}

    def _log(self, text: str) -> None:
        if self.fd >= 0:
            os.write(self.fd, (text + "\n").encode())

    def check(self) -> None:
        if not os.path.isdir(os.path.dirname(self.config["log"]) or "."):
            raise DeviceError(self.name, "", "log", "its folder does not exist")

    def configure(self) -> None:
        self.fd = os.open(self.config["log"], os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
        with open(self.config["log"] + ".pid", "w") as pid_file:  # which process to kill -9 in a test
            pid_file.write(str(os.getpid()))
        self._log("configure")
        if self.config["fail_in"] == "configure":
            raise DeviceError(self.name, "", "fail_in", "the device did not answer (as asked)")

    def activate(self) -> None:
        self._log("activate")
        if self.config["fail_in"] == "activate":
            raise OSError("activate failed (as asked)")

    def read(self, y: np.ndarray) -> None:
        if self.config["fail_in"] == "read":
            raise OSError("read failed (as asked)")
        if self.config["fail_in"] == "estop" and self.last[0] >= 3:  # what an E-stop input does (io/gpio.py)
            raise EmergencyStop(self.name, "estop", "falling", time.monotonic_ns())
        n = min(len(y), len(self.last))
        y[:n] = self.last[:n] * self.config["gain"]
        if 0 <= self.config.get("nan_reading_at", -1.0) <= self.last[0]:  # an ADC glitch, a f32 frame of NaN bits
            y[0] = math.nan

    def write(self, u: np.ndarray) -> None:
        if self.config["fail_in"] == "write":
            raise OSError("write failed (as asked)")
        self.last[:] = u
        self._log("write " + " ".join(repr(float(v)) for v in u))

    def write_safe(self, u: np.ndarray) -> None:
        self.last[:] = u
        self._log("safe " + " ".join(repr(float(v)) for v in u))

    def write_safe_for_dead_task(self, u: np.ndarray) -> str:
        """What a CAN or GPIO driver does from the supervisor: the safe values, from outside."""
        with open(self.config["log"], "a") as log:
            log.write("safe from the supervisor " + " ".join(repr(float(v)) for v in u) + "\n")
        return "logged the safe values"

    def deactivate(self) -> None:
        self._log("deactivate")

    def close(self) -> None:
        self._log("close")
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


class MirrorTwin(Runnable):
    """The LogDevice's twin: reading = gain × command."""

    def __init__(self, n: int = 1, gain: float = 1.0) -> None:
        self.n_inputs = self.n_outputs = n
        self.gain = gain

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        np.multiply(u, self.gain, out=y)


class NanTwin(MirrorTwin):
    """The LogDevice's twin with ``nan_reading_at``: reading NaN once the command has reached ``nan_at``."""

    def __init__(self, nan_at: float) -> None:
        super().__init__(1, 1.0)
        self.nan_at = nan_at

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        y[0] = math.nan if u[0] >= self.nan_at else u[0]


def read_log(path: str | os.PathLike[str]) -> list[str]:
    if not os.path.exists(path):
        return []
    with open(path) as stream:
        return stream.read().splitlines()


class Echo(Runnable):
    """y[0] = u[0] + 1 (its device mirrors y back into u); NaN at ``nan_at``; stuck or slow on request."""

    n_inputs = 1
    n_outputs = 1

    def __init__(self, nan_at: int = -1, raise_at: int = -1, stuck_at: int = -1, slow_s: float = 0.0) -> None:
        self.nan_at, self.raise_at, self.stuck_at, self.slow_s = nan_at, raise_at, stuck_at, slow_s

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        cycle = self.tick.cycle
        y[0] = math.nan if cycle == self.nan_at else u[0] + 1.0
        if 0 <= self.raise_at <= cycle:  # at or after: a loaded machine may skip that release
            raise ZeroDivisionError("step raised (as asked)")
        if 0 <= self.stuck_at <= cycle:  # at or after: a loaded machine may skip that release
            while True:
                pass
        if self.slow_s:
            time.sleep(self.slow_s)


class CycleAndReading(Runnable):
    """y[0] = the cycle + 1 (so the command a let device writes at release k is k); u[0] is a reading."""

    n_inputs = 1
    n_outputs = 1

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        y[0] = self.tick.cycle + 1.0


class _LinkThatGoesDown:
    """A stand-in for a CAN socket (a UNIX socket pair's end, for poll and recv) whose sends fail
    with ENETDOWN from the ``down_at``-th on, as a SocketCAN socket's do once its interface is down."""

    def __init__(self, sock: Any, down_at: int) -> None:
        self.sock, self.down_at, self.sent = sock, down_at, 0

    def send(self, frame: Any) -> int:
        self.sent += 1
        if self.sent >= self.down_at:
            raise OSError(errno.ENETDOWN, os.strerror(errno.ENETDOWN))
        return len(frame)

    def __getattr__(self, name: str) -> Any:  # fileno, setblocking, recv_into, close
        return getattr(self.sock, name)


class CanLinkGoesDown(CanDevice):
    """A CAN device whose link goes down mid-run, where the kernel has no CAN: its socket is a
    UNIX socket pair's end whose sends fail with ENETDOWN from the ``down_at_send``-th send on.
    Only the Python reference runs over it (the C cycle sends on the descriptor itself)."""

    kind = "test_can_link_goes_down"
    settings: ClassVar[dict[str, Setting]] = {
        **CanDevice.settings, "down_at_send": Setting(int, 20, "the send that fails first (ENETDOWN)")}

    def check(self) -> None:
        pass  # no CAN interface to look at: the socket pair stands in for it

    def configure(self) -> None:
        from rtloop.io.cansocket import CanSocket

        ours, self._peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.attach(CanSocket(self.interface, False, self.received, f"devices.{self.name}",
                              sock=_LinkThatGoesDown(ours, self.config["down_at_send"])))

    def close(self) -> None:
        super().close()
        self._peer.close()
