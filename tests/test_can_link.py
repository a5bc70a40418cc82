"""CAN on any machine (a UNIX socket pair in the bus's place): receive timeouts below a millisecond,
and a link that goes down mid-run (issue 29). Both twins: the C cycle (io/_devio.c) and the Python
reference (io/can.py, io/cansocket.py)."""

from __future__ import annotations

import errno
import socket
import time

import numpy as np
import pytest

from rtloop.io.device import build_device

RECEIVE = {"id": 0x180, "on_missing": "stale", "signals": [{"name": "position", "start_byte": 0, "type": "i32"}]}
SEND = [{"id": 0x200, "signals": [{"name": "torque", "start_byte": 0, "type": "i16", "scale": 0.01}]}]


@pytest.fixture(params=["c", "python"])
def twin(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """The C cycle and its Python reference (the switch is read when the device attaches its socket)."""
    if request.param == "c":
        pytest.importorskip("rtloop.io._devio", reason="the devices' C part was not built (no compiler)")
        monkeypatch.delenv("RTLOOP_PURE_PYTHON", raising=False)
    else:
        monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
    return request.param


def drive_on_a_pair(twin: str, timeout_ms: float):
    from rtloop.io.cansocket import CanSocket

    device = build_device("can", "drive", {"interface": "vcan0", "send": SEND,
                                           "receive": [{**RECEIVE, "timeout_ms": timeout_ms}]}, "app.toml")
    ours, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    device.attach(CanSocket("pair", False, device.received, "devices.drive", sock=ours))
    assert (device._cycle is not None) == (twin == "c")
    return device, peer


def test_a_receive_timeout_below_a_millisecond_is_honoured(twin: str) -> None:
    """``timeout_ms = 0.2`` waited poll(1), a whole millisecond (a whole period at 1 kHz), exactly when
    ``on_missing = "stale"`` should keep the loop going. poll() never returns before its timeout, so
    the shortest of several waits shows the resolution: under a millisecond now, at least one before."""
    device, peer = drive_on_a_pair(twin, timeout_ms=0.2)
    y = np.zeros(1)
    waits_ns = []
    try:
        for _ in range(20):
            start_ns = time.monotonic_ns()
            device.read(y)  # the answer never comes: a stale read after the timeout
            waits_ns.append(time.monotonic_ns() - start_ns)
    finally:
        device.socket.close()
        peer.close()
    assert device.stale_reads == 20
    assert min(waits_ns) >= 200_000  # it did wait its timeout
    assert min(waits_ns) < 900_000, f"shortest wait {min(waits_ns) / 1e6:.3f} ms for a 0.2 ms timeout"
