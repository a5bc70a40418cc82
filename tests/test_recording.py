"""run.mcap holds the same values as signals.csv, read back with an independent reader."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest

import rtloop

EXAMPLES = Path(__file__).parent.parent / "examples"


def test_mcap_signals_equal_signals_csv_and_timing_equals_timing_csv(tmp_path: Path) -> None:
    mcap_reader = pytest.importorskip("mcap.reader")
    decoder = pytest.importorskip("mcap_ros2.decoder")
    from rtloop.app.appfile import load_app

    app = load_app(EXAMPLES / "jiwy" / "jiwy.toml")
    app.feed("setpoint", EXAMPLES / "jiwy" / "setpoints" / "step.csv")
    rtloop.simulate(app, 1.0, tmp_path)
    with open(tmp_path / "signals.csv", newline="") as file:
        rows = list(csv.reader(file))
    header, rows = rows[0], rows[1:]
    with open(tmp_path / "run.mcap", "rb") as file:
        reader = mcap_reader.make_reader(file, decoder_factories=[decoder.DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        signals, timing = [], []
        for schema, channel, message, ros_msg in reader.iter_decoded_messages():
            if channel.topic == "/rtloop/signals":
                assert schema.name == "sensor_msgs/msg/JointState" and channel.message_encoding == "cdr"
                signals.append((message.log_time, list(ros_msg.name), list(ros_msg.position)))
            elif channel.topic == "/rtloop/timing/plant":
                timing.append((ros_msg.cycle, ros_msg.release_ns, ros_msg.start_ns, ros_msg.end_ns))
    assert len(signals) == len(rows) == 1001  # the initial outputs at t = 0, then one row per tick
    t0_wall = signals[0][0]
    for (log_time, names, values), row in zip(signals, rows, strict=True):
        assert names == header[1:]
        assert (log_time - t0_wall) / 1e9 == pytest.approx(float(row[0]), abs=1e-12)
        assert [repr(v) for v in values] == row[1:]  # bit for bit
    with open(tmp_path / "timing.csv", newline="") as file:
        plant_rows = [tuple(int(x) for x in r[1:]) for r in csv.reader(file) if r[0] == "plant"]
    assert timing == plant_rows
    assert not any(math.isnan(v) for _, _, values in signals for v in values)


def test_summary_names_signals_and_the_report_labels_them(tmp_path: Path) -> None:
    import json

    from rtloop.app.appfile import load_app
    from rtloop.report.figures import names_from_summary

    app = load_app(EXAMPLES / "jiwy" / "jiwy.toml")
    rtloop.simulate(app, 0.05, tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["tasks"]["plant"]["output_names"] == ["AnglePan", "AngleTilt"]
    names = names_from_summary(summary)
    assert names["plant.y[1]"] == "AngleTilt" and names["controller.u[2]"] == "SetPointPan"
