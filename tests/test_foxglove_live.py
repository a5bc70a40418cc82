"""`rtloop run --foxglove`: a plain WebSocket client (subprotocol foxglove.sdk.v1, or its older name
foxglove.websocket.v1) sees the run live
and writes an input port through the same checks as the ROS 2 talker.

The client is the `websockets` package speaking the Foxglove WebSocket protocol by hand
(JSON ops, binary frames `0x01 | u32 id | u64 log time | CDR`); the CDR is decoded here
with `struct`, not with rtloop.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import unique_name
from foxglove_client import connect, handshake, run_with_live_view, subscribe
from rtloop.app.builder import App
from rtloop.errors import AppError

pytest.importorskip("foxglove")
websockets_sync = pytest.importorskip("websockets.sync.client")

APP = """\
name = "fox_{suffix}"

[tasks.gain]
runnable = "rt_test_runnables:Gain"
args = {{ n = 2, gain = 2.0 }}
period_ns = 1_000_000
priority = 70

[ports.setpoint]
to = "gain.u[0:2]"

[record]
signals = ["gain.y"]

[foxglove]
port = 0
inputs = ["setpoint"]
"""


def read_string(data: bytes, offset: int) -> tuple[str, int]:
    offset += -(offset - 4) % 4
    (length,) = struct.unpack_from("<I", data, offset)
    text = data[offset + 4: offset + 4 + length - 1].decode()
    return text, offset + 4 + length


def decode_joint_state(data: bytes) -> tuple[list[str], list[float]]:
    assert data[:4] == b"\x00\x01\x00\x00"  # CDR, little endian
    _frame_id, offset = read_string(data, 12)  # after the header's stamp (sec, nanosec)
    (count,) = struct.unpack_from("<I", data, offset + (-(offset - 4) % 4))
    offset += -(offset - 4) % 4 + 4
    names = []
    for _ in range(count):
        name, offset = read_string(data, offset)
        names.append(name)
    offset += -(offset - 4) % 4
    (count,) = struct.unpack_from("<I", data, offset)
    offset += 4
    offset += -(offset - 4) % 8
    return names, list(struct.unpack_from(f"<{count}d", data, offset))


@pytest.mark.rt
@pytest.mark.parametrize("subprotocol", ["foxglove.sdk.v1", "foxglove.websocket.v1"])
def test_foxglove_client_receives_signals_and_timing_and_writes_a_port(tmp_path: Path, rtloop_env,
                                                                       subprotocol: str) -> None:
    app_file = tmp_path / "fox.toml"
    app_file.write_text(APP.format(suffix=unique_name("live")))
    out = tmp_path / "out"
    with run_with_live_view(app_file, out, 60, rtloop_env) as (run, url):  # ended once seen
        assert url.startswith("ws://localhost:")
        with connect(url, subprotocol) as client:
            assert client.subprotocol == subprotocol  # the name the client offered, answered as offered
            info, channels = handshake(client, {"/rtloop/signals", "/rtloop/timing/gain"})
            assert "clientPublish" in info["capabilities"]
            subscribe(client, {1: channels["/rtloop/signals"], 2: channels["/rtloop/timing/gain"]})
            client.send(json.dumps({"op": "advertise", "channels": [
                {"id": 7, "topic": "/rtloop/ports/setpoint", "encoding": "json",
                 "schemaName": "std_msgs/msg/Float64MultiArray"}]}))
            publish = b"\x01" + struct.pack("<I", 7)
            client.send(publish + json.dumps({"data": [1.0]}).encode())  # wrong length: rejected
            client.send(publish + b'{"data": [NaN, 1.0]}')  # not finite: rejected
            client.send(publish + json.dumps({"data": [0.5, 0.25]}).encode())
            rows, timing, followed = [], 0, False
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and not (followed and timing > 100 and len(rows) > 100):
                message = client.recv(timeout=30)
                if isinstance(message, str):
                    continue
                assert message[0] == 1
                subscription, _log_time_ns = struct.unpack_from("<IQ", message, 1)
                payload = message[13:]
                if subscription == 1:
                    names, values = decode_joint_state(payload)
                    assert names == ["gain.y[0]", "gain.y[1]"]
                    rows.append(values)
                    followed = followed or values == [1.0, 0.5]  # y = 2 · setpoint
                else:
                    _cycle, release, start, end, latency, exec_ns = struct.unpack_from("<Q5q", payload, 4)
                    assert latency == start - release and exec_ns == end - start
                    timing += 1
            assert len(rows) > 100 and timing > 100, (len(rows), timing)
            assert followed, f"the task never followed the setpoint sent from Foxglove; last rows {rows[-3:]}"
            assert not any(v != v for row in rows for v in row), "a rejected NaN reached the task"
    assert run.returncode == 0
    live = json.loads((out / "summary.json").read_text())["bridges"]["foxglove"]
    assert live["input_written"] >= 1
    assert live["input_rejected_by_reason"]["length"] == 1 and live["input_rejected_by_reason"]["nonfinite"] == 1


def test_foxglove_settings_are_checked() -> None:
    from rt_test_runnables import Gain

    app = App("fox_check")
    app.add_task("g", Gain(2), period_ns=1_000_000)
    app.port("setpoint", to=app.tasks["g"].u[0:2])
    assert app.serve_foxglove(0, inputs=["setpoint"]).host == "127.0.0.1"
    with pytest.raises(AppError, match="no input port 'nope'"):
        app.serve_foxglove(8765, inputs=["nope"])
    with pytest.raises(AppError, match=r"0\.\.65535"):
        app.serve_foxglove(70000)


def test_missing_foxglove_sdk_is_one_line(tmp_path: Path, rtloop_env) -> None:
    app_file = tmp_path / "fox.toml"
    app_file.write_text(APP.format(suffix=unique_name("missing")))
    blocker = tmp_path / "blocker"
    blocker.mkdir()
    (blocker / "foxglove.py").write_text("raise ImportError('hidden for this test')\n")
    env = {**rtloop_env, "PYTHONPATH": f"{blocker}:{rtloop_env['PYTHONPATH']}"}
    result = subprocess.run([sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--duration", "1", "--out",
                             str(tmp_path / "out"), "--quiet"], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode != 0
    assert result.stderr.strip().splitlines() == [
        "rtloop run: the Foxglove live view needs foxglove-sdk: pip install 'rtloop[live]'"]


def test_the_front_accepts_both_names_and_refuses_others() -> None:
    foxglove = pytest.importorskip("foxglove", reason="the live view needs foxglove-sdk (pip install 'rtloop[live]')")
    from rtloop.ros.subprotocol import SubprotocolFront

    server = foxglove.start_server(name="front", host="127.0.0.1", port=0, context=foxglove.Context())
    front = SubprotocolFront("127.0.0.1", 0, server.port)
    try:
        for offered in (["foxglove.websocket.v1"], ["foxglove.sdk.v1"], ["foxglove.websocket.v1", "foxglove.sdk.v1"]):
            with websockets_sync.connect(f"ws://127.0.0.1:{front.port}", subprotocols=offered,
                                         open_timeout=10) as client:
                assert client.subprotocol in offered
                assert json.loads(client.recv(timeout=10))["op"] == "serverInfo"
        with pytest.raises(Exception, match="400"):
            websockets_sync.connect(f"ws://127.0.0.1:{front.port}", subprotocols=["chat.v2"], open_timeout=10)
    finally:
        front.close()
        server.stop()


def test_only_the_handshake_header_is_renamed() -> None:
    from rtloop.ros.subprotocol import rename_offer

    request = (b"GET / HTTP/1.1\r\nHost: x\r\nsec-websocket-protocol: foxglove.websocket.v1\r\n"
               b"X-Note: foxglove.websocket.v1\r\n\r\n")
    renamed, alias = rename_offer(request)
    assert alias == "foxglove.websocket.v1"
    assert b"Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n" in renamed and b"X-Note: foxglove.websocket.v1" in renamed
    assert rename_offer(b"GET / HTTP/1.1\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n")[1] is None
