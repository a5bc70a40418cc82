"""examples/jiwy_spi anywhere: its frame as declared, the FPGA model (the SPI device's twin),
``rtloop simulate`` following the setpoint step, and the model's server (``fpga_server.py``)
answering the SPI device's own exchanges as the twin does, bit for bit. (The server on the test
guest's SPI bus, a whole run against it: tests/test_io_jiwy_spi.py.)"""

from __future__ import annotations

import csv
import math
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "jiwy_spi"


@pytest.fixture
def models(monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE))
    import jiwy_spi_models

    return jiwy_spi_models


def test_the_app_file_declares_the_frame_the_model_speaks(models):
    fpga = tomllib.loads((EXAMPLE / "jiwy_spi.toml").read_text())["devices"]["fpga"]
    assert (fpga["send"], fpga["receive"], fpga["length"]) == (models.FRAME_SEND, models.FRAME_RECEIVE,
                                                               models.FRAME_LENGTH)


def test_the_fpga_model_drives_nothing_until_enabled_and_counts_whole_encoder_steps(models):
    fpga = models.FpgaModel(step_size_s=0.005)
    fpga.prerun()
    y = np.zeros(3)
    for _ in range(50):  # a duty without the enable bit: the H-bridge stays off
        fpga.step(np.array([0.7, -0.3, 0.0]), y)
    assert not fpga.enabled and list(y) == [0.0, 0.0, 0.0]
    per_count = 2 * math.pi / (2000 * 19)
    fpga.step(np.array([1.5, 0.0, 1.0]), y)  # past the duty's range: clamped to 1
    assert fpga.enabled and fpga.duty == (1.0, 0.0) and y[2] == 1.0
    for _ in range(3_000):  # 5 % duty on pan for 15 s: many turns, the 16-bit count wraps many times
        fpga.step(np.array([0.05, 0.0, 1.0]), y)
        assert y[0] == round(fpga.states[1] / per_count) * per_count  # the camera angle in whole counts
    assert y[0] > 4 * 65536 * per_count  # unwrapped past the field four times over
    fpga.step(np.array([0.0, 0.0, 0.0]), y)  # the safe state
    assert not fpga.enabled and fpga.duty == (0.0, 0.0) and y[2] == 0.0


def test_simulate_follows_the_setpoint_step(tmp_path):
    run = subprocess.run([sys.executable, "-m", "rtloop", "simulate", str(EXAMPLE / "jiwy_spi.toml"), "--duration",
                          "4", "--out", str(tmp_path / "sim"), "-q"], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    with open(tmp_path / "sim" / "signals.csv") as signals:
        rows = list(csv.DictReader(signals))
    last = rows[-1]
    assert float(last["controller.SetPointPan"]) == 0.5 and float(last["controller.SetPointTilt"]) == 0.3
    assert abs(float(last["controller.encoder_pan"]) - 0.5) < 0.005
    assert abs(float(last["controller.encoder_tilt"]) - 0.3) < 0.005
    assert all(float(row["fpga.enable"]) == 1.0 and abs(float(row["fpga.pwm_pan"])) <= 1.0 for row in rows)


@pytest.fixture
def server_module(monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE))
    import fpga_server

    return fpga_server


def spi_device_answered_by(server, monkeypatch):
    """The example's SPI device (the Python cycle) whose transfers the FPGA server answers in place
    of spidev: each SPI_IOC_MESSAGE(1) hands the frame sent to ``server.exchange``."""
    from rtloop.io import spi
    from rtloop.io.device import build_device

    fpga = tomllib.loads((EXAMPLE / "jiwy_spi.toml").read_text())["devices"]["fpga"]
    table = {key: fpga[key] for key in ("device", "speed_hz", "mode", "length", "counter", "on_error", "send",
                                        "receive")}
    monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
    device = build_device("spi", "fpga", table, "jiwy_spi.toml")
    device._build_frames()
    monkeypatch.delenv("RTLOOP_PURE_PYTHON")

    class Bus:
        @staticmethod
        def ioctl(fd, request, argument, name):
            device._rx[:] = server.exchange(bytes(device._tx))

    monkeypatch.setattr(spi, "rt", Bus)
    return device


def test_the_server_answers_every_exchange_of_the_spi_device_as_the_twin_does(models, server_module, monkeypatch):
    """The device's exchanges (configure's safe frame before T0, the first cycle's read in a cycle
    that reads before it writes, a write per cycle, the safe frame at the stop) each step the
    served model once, as the twin steps in ``rtloop simulate``: the readings are equal bit for
    bit, and so are the steps taken."""
    from rtloop.io.twin import TwinDevice

    server = server_module.FpgaServer(models.FpgaModel(step_size_s=0.005))
    server.model.prerun()
    device = spi_device_answered_by(server, monkeypatch)
    twin_model = models.FpgaModel(step_size_s=0.005)
    twin = TwinDevice("fpga", twin_model, like=device, safe=[0.0, 0.0, 0.0])
    twin.configure()
    safe = np.zeros(3)
    device.write_safe(safe)  # configure: held safe until T0
    twin.write_safe(safe)
    rng = np.random.default_rng(32)
    y_device, y_twin = np.zeros(3), np.zeros(3)
    for cycle in range(400):
        device.read(y_device)
        twin.read(y_twin)
        assert y_device.tobytes() == y_twin.tobytes(), (cycle, y_device, y_twin)
        u = np.array([rng.uniform(-1.2, 1.2), rng.uniform(-1.2, 1.2), 1.0 if cycle > 3 else 0.0])
        device.write(u)
        twin.write(u)
    assert server.transfers == 1 + 1 + 400  # configure's, the first cycle's read, one write per cycle
    twin.read(y_twin)  # the twin steps on the last commands when they are read; the server did at their transfer
    assert twin_model.states == server.model.states and y_twin.tobytes() == server.readings.tobytes()
    device.write_safe(safe)  # the stop: the last frame the FPGA sees is PWM 0 and enable off
    assert list(server.commands) == [0.0, 0.0, 0.0] and not server.model.enabled
    assert server.bad_frames == 0 and device.transfers_rejected == 0 and abs(y_device[0]) > 0.01


def test_the_first_cycle_asks_the_device_again_after_configure_s_safe_frame(models, server_module, monkeypatch):
    """Configure's safe frame goes out before T0; its answer is not the first cycle's reading (that
    would be as old as the start-up): the first read transfers again."""
    server = server_module.FpgaServer(models.FpgaModel(step_size_s=0.005))
    server.model.prerun()
    device = spi_device_answered_by(server, monkeypatch)
    device.write_safe(np.zeros(3))
    assert server.transfers == 1
    device.read(np.zeros(3))
    assert server.transfers == 2
    device.write(np.array([0.5, 0.5, 1.0]))
    device.read(np.zeros(3))  # an answer came since the last read: no transfer
    assert server.transfers == 3


def test_the_server_obeys_no_bad_frame_and_answers_with_the_counter_before(models, server_module):
    from rtloop.io.spiframe import crc16_ccitt, seal

    server = server_module.FpgaServer(models.FpgaModel(step_size_s=0.005))
    server.model.prerun()
    frame = bytearray(models.FRAME_LENGTH)
    server.model.send.pack_into(frame, 0, np.array([0.25, -0.5, 1.0]))
    seal(frame, memoryview(frame)[:-2], 7)
    answer = server.exchange(bytes(frame))
    assert answer[0] == 0 and crc16_ccitt(answer[:-2]) == int.from_bytes(answer[-2:], "big")  # none before
    assert list(server.commands) == [0.25, -0.5, 1.0] and server.model.enabled
    frame[2] ^= 0x40  # a bit flipped on the wire: the CRC no longer matches
    answer = server.exchange(bytes(frame))
    assert answer[0] == 7 and server.bad_frames == 1 and list(server.commands) == [0.25, -0.5, 1.0]
    server.exchange(b"\xff" * models.FRAME_LENGTH)  # nobody driving MOSI: not obeyed either
    assert server.bad_frames == 2 and list(server.commands) == [0.25, -0.5, 1.0]


def test_the_server_loop_answers_one_transfer_per_read_and_logs_what_the_model_saw(models, server_module,
                                                                                    tmp_path):
    """``serve`` on a socket pair that keeps message boundaries, as the controller module's device
    does (one read: one whole transfer; one write: its answer)."""
    import io
    import socket
    import threading

    from rtloop.io.spiframe import seal

    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    log = io.StringIO()
    server = server_module.FpgaServer(models.FpgaModel(step_size_s=0.005), log)
    server.model.prerun()
    thread = threading.Thread(target=server_module.serve, args=(theirs.fileno(), server))
    thread.start()
    try:
        frame = bytearray(models.FRAME_LENGTH)
        for counter, u in enumerate(([0.0, 0.0, 0.0], [0.3, 0.1, 1.0], [0.0, 0.0, 0.0])):
            server.model.send.pack_into(frame, 0, np.array(u))
            seal(frame, memoryview(frame)[:-2], counter)
            ours.send(frame)
            answer = ours.recv(4096)
            assert len(answer) == models.FRAME_LENGTH and answer[0] == max(counter - 1, 0)
    finally:
        ours.close()  # EOF: the loop ends
        thread.join(timeout=10)
        theirs.close()
    rows = list(csv.DictReader(io.StringIO(log.getvalue())))
    assert [(row["counter"], row["good"], row["enable"], row["answered"]) for row in rows] == [
        ("0", "1", "0.0", "1"), ("1", "1", "1.0", "1"), ("2", "1", "0.0", "1")]
    assert float(rows[1]["pwm_pan"]) == 0.3 and float(rows[2]["pwm_pan"]) == 0.0


def test_a_machine_without_spidev_is_told_how_to_get_one_or_to_simulate(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    from rtloop.errors import DeviceError
    from rtloop.io.device import build_device

    listdir = os.listdir
    monkeypatch.setattr(os, "listdir", lambda path=".": [n for n in listdir(path) if not n.startswith("spidev")]
                        if str(path) == "/dev" else listdir(path))  # a machine without any (this VM, a laptop)
    fields = [{"name": "pwm", "start_byte": 1, "type": "i16"}]
    device = build_device("spi", "fpga", {"device": "/dev/spidev9.9", "length": 8, "send": fields,
                                          "receive": fields}, "app.toml")
    with pytest.raises(DeviceError) as refused:
        device.check()
    said = str(refused.value)  # (no app file named: the device built here has none)
    assert said.startswith(": devices.fpga.device: no SPI device /dev/spidev9.9 (this machine has no spidev "
                           "device: enable its SPI controller (a Raspberry Pi: dtparam=spi=on"), said
    assert "rtloop simulate runs the device's twin" in said and "\n" not in said, said
