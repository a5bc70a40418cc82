"""examples/jiwy_spi anywhere: its frame as declared, the FPGA model (the SPI device's twin) and
``rtloop simulate`` following the setpoint step. (Answering for real over /dev/spidev in the
PREEMPT_RT guest is not built yet: docs/bench.md.)"""

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
