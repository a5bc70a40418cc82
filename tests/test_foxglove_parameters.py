"""Live tuning from Foxglove and Lichtblick (issue 30, defect 9): the live view serves the app's live
parameters with the Foxglove WebSocket protocol's ``parameters`` capability. The client here is the
`websockets` package speaking the published protocol (foxglove.websocket.v1: getParameters,
setParameters, parameterValues) by hand; the change shows in the run's inputs.csv, its signals and
its replay, and a value outside the port's range is refused."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from conftest import unique_name
from foxglove_client import connect, handshake, run_with_live_view, subscribe
from rtloop.record.csvfiles import read_inputs_csv
from rtloop.runtime.replay import replay

pytest.importorskip("foxglove")
pytest.importorskip("websockets.sync.client")

APP = """\
name = "{name}"

[tasks.gain]
runnable = "rt_test_runnables:TunedGain"
period_ns = 2_000_000
priority = 70

[ports.gains]
to = "gain.k"
range = [0.0, 10.0]

[record]
signals = ["gain.y", "gain.u"]

[foxglove]
port = 0
inputs = ["gains"]
"""


def answer(client, op: str, request_id: str, timeout_s: float = 20.0) -> dict:
    """The next text message ``op`` with ``id`` (the server's other messages are passed over)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        message = client.recv(timeout=timeout_s)
        if isinstance(message, str):  # (signal rows, binary, are passed over)
            decoded = json.loads(message)
            if decoded["op"] == op and decoded.get("id") == request_id:
                return decoded
    pytest.fail(f"no {op} with id {request_id!r} within {timeout_s} s")


def wait_for_rows(client, timeout_s: float = 30.0) -> dict:
    """Subscribe to the signals and wait for the first rows (they flow from T0 on); the server's info."""
    info, channels = handshake(client, {"/rtloop/signals"})
    subscribe(client, {1: channels["/rtloop/signals"]})
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if isinstance(client.recv(timeout=timeout_s), bytes):
            return info
    pytest.fail("no signal rows within the time")


@pytest.mark.rt
def test_a_foxglove_client_tunes_a_live_parameter_and_the_replay_repeats_it(tmp_path: Path, rtloop_env) -> None:
    app_file = tmp_path / "tune.toml"
    app_file.write_text(APP.format(name=unique_name("fox_tune")))
    out = tmp_path / "out"
    with run_with_live_view(app_file, out, 60, rtloop_env) as (run, url), connect(url) as client:  # ended once seen
        info = wait_for_rows(client)  # the run is past T0: the tuning lands in the middle of it
        assert "parameters" in info["capabilities"], info
        client.send(json.dumps({"op": "getParameters", "parameterNames": [], "id": "all"}))
        assert answer(client, "parameterValues", "all")["parameters"] == [{"name": "gain.k", "value": 2.0,
                                                                            "type": "float64"}]
        client.send(json.dumps({"op": "setParameters", "id": "far",
                                "parameters": [{"name": "gain.k", "value": 50.0}]}))  # outside range
        assert [p["value"] for p in answer(client, "parameterValues", "far")["parameters"]] == [2.0]
        time.sleep(0.3)
        client.send(json.dumps({"op": "setParameters", "id": "tune",
                                "parameters": [{"name": "gain.k", "value": 3.5}]}))
        assert [p["value"] for p in answer(client, "parameterValues", "tune")["parameters"]] == [3.5]
        time.sleep(0.5)  # the task takes it at its next release
        client.send(json.dumps({"op": "getParameters", "parameterNames": ["gain.k"], "id": "now"}))
        assert [p["value"] for p in answer(client, "parameterValues", "now")["parameters"]] == [3.5]
    assert run.returncode == 0
    taken = [(port, values) for _task, _cycle, port, values in read_inputs_csv(out / "inputs.csv")]
    assert taken == [("gains", [3.5])], taken  # logged like any port write; the refused 50 never reached it
    rows = (out / "signals.csv").read_text().splitlines()
    column = rows[0].split(",").index("gain.y[0]")
    outputs = [float(row.split(",")[column]) for row in rows[1:]]
    assert outputs[1] == 2.0 and outputs[-1] == 3.5
    live = json.loads((out / "summary.json").read_text())["bridges"]["foxglove"]
    assert live["parameters"] == ["gain.k"] and live["parameters_set"] == 1 and live["parameters_refused"] == 1
    replayed = replay(out, tmp_path / "replay")
    assert replayed.equal and replayed.rows_compared > 100, replayed.divergence or replayed.cannot
