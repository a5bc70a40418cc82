"""Servo buses without a pty: the packets (against dynamixel-sdk's own), the units, the checks at load
and at configure, a silent servo and a hardware error, against the servo model in process."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from rtloop.errors import DeviceError, DeviceFault, DeviceMismatch, DeviceNotReady
from rtloop.io.device import build_device
from rtloop.io.servos.line import ModelLine
from rtloop.io.servos.model import Faults, build_bus
from rtloop.io.servos.protocol import PROTOCOLS, SyncWrite, crc16
from rtloop.io.servos.tables import DYNAMIXEL_X, FEETECH_STS

PAN_TILT = [{"name": "pan", "id": 1, "model": "XM430-W350", "range_rad": [-1.5, 1.5]},
            {"name": "tilt", "id": 2, "model": "XM430-W350", "range_rad": [-1.0, 1.0], "direction": -1}]


def bus_device(kind: str = "dynamixel", servos: list[dict[str, Any]] | None = None, **settings: Any) -> Any:
    return build_device(kind, "arm", {"port": "/dev/null", "servos": servos or PAN_TILT, **settings}, "app.toml")


def attached(device: Any, ids: list[int] | None = None, models: list[str] | None = None,
             faults: dict[int, Faults] | None = None) -> Any:
    """``device`` on a bus model in process (the twin's way), configured and activated."""
    specs = device.specs
    bus = build_bus(device.protocol_name, ids or [s.servo_id for s in specs],
                    models or [s.model.name for s in specs], 0.002, faults=faults)
    device.attach(ModelLine(bus))
    device.write_safe(np.zeros(device.n_inputs))
    device.activate()
    return bus


def test_the_crc_is_dynamixels() -> None:
    assert crc16(b"123456789") == 0xFEE8  # CRC-16/UMTS check value


def test_a_feetech_ping_is_the_documented_bytes() -> None:
    assert bytes(PROTOCOLS["feetech"].packet(1, 0x01, b"")) == bytes([0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFB])


class _Capture:
    """A dynamixel-sdk port handler that keeps what would be written."""

    def __init__(self) -> None:
        self.written = b""
        self.is_using = False

    def clearPort(self) -> None:
        pass

    def writePort(self, packet: list[int]) -> int:
        self.written = bytes(packet)
        return len(packet)


@pytest.mark.parametrize("goals", [[2048, 100], [-3, -1], [4095, 0]])
def test_a_sync_write_is_the_same_bytes_as_dynamixel_sdks(goals: list[int]) -> None:
    sdk = pytest.importorskip("dynamixel_sdk", reason="dynamixel-sdk is not installed (the test extra has it)")
    port = _Capture()
    group = sdk.GroupSyncWrite(port, sdk.Protocol2PacketHandler(), 116, 4)
    for servo_id, goal in zip((1, 2), goals, strict=True):
        group.addParam(servo_id, list((goal & 0xFFFFFFFF).to_bytes(4, "little")))
    group.txPacket()
    ours = SyncWrite(PROTOCOLS["dynamixel"], DYNAMIXEL_X.fields["goal_position"], [1, 2])
    ours.values.encode(np.array([float(g if g < 1 << 31 else g - (1 << 32)) for g in goals]))
    assert bytes(ours.seal()) == port.written


def test_ff_ff_fd_in_the_values_is_stuffed() -> None:
    """Protocol 2.0's byte stuffing: FF FF FD in the parameters goes out as FF FF FD FD, the length
    counts the extra byte and the CRC covers the stuffed packet. (dynamixel-sdk 4.x's Python
    ``addStuffing`` builds the longer packet in a new list its caller never sees: it sends this one
    unstuffed, which a servo reads as a new header.)"""
    ours = SyncWrite(PROTOCOLS["dynamixel"], DYNAMIXEL_X.fields["goal_position"], [1, 2])
    ours.values.encode(np.array([float(0x00FDFFFF), 100.0]))
    body = bytes([0x83, 0x74, 0x00, 0x04, 0x00, 0x01, 0xFF, 0xFF, 0xFD, 0xFD, 0x00, 0x02, 100, 0, 0, 0])
    expected = bytearray(b"\xff\xff\xfd\x00\xfe" + (len(body) + 2).to_bytes(2, "little") + body)
    expected += crc16(expected).to_bytes(2, "little")
    assert bytes(ours.seal()) == bytes(expected)
    bus = build_bus("dynamixel", [1, 2], ["XM430-W350"], 0.002)
    bus.servos[1].set("torque_enable", 0)
    assert bus.receive(bytes(expected)) == b""  # a sync write gets no answer
    assert bus.servos[1].get("goal_position") == 0x00FDFFFF  # the model took the unstuffed value


def test_sign_and_magnitude_values_round_trip() -> None:
    ours = SyncWrite(PROTOCOLS["feetech"], FEETECH_STS.fields["goal_velocity"], [1, 2, 3])
    ours.values.encode(np.array([-5.0, 7.0, 0.0]))
    assert bytes(ours.packet[8:10]) == (0x8005).to_bytes(2, "little")
    back = np.zeros(3)
    ours.values.decode(back)
    assert back.tolist() == [-5.0, 7.0, 0.0]


# --- bad input at load: one line naming the key -------------------------------------------------------

@pytest.mark.parametrize(("servos", "key", "words"), [
    ([{**PAN_TILT[0], "range_rad": [-3.5, 3.5]}], "servos[0].range_rad", "outside the servo's 0..4095"),
    ([{**PAN_TILT[0], "range_rad": [-1e308, 1e308]}], "servos[0].range_rad", "outside the servo's 0..4095"),
    ([{**PAN_TILT[0], "model": "XM999"}], "servos[0].model", "is not a dynamixel model"),
    ([PAN_TILT[0], {**PAN_TILT[1], "id": 1}], "servos[1].id", "also servos[0]'s"),
    ([{**PAN_TILT[0], "direction": 2}], "servos[0].direction", "expected 1 or -1"),
    ([{**PAN_TILT[0], "speed": 2}], "servos[0].speed", "unknown key"),
])
def test_bad_servo_settings_are_one_line(servos: list[dict[str, Any]], key: str, words: str) -> None:
    with pytest.raises(DeviceError) as caught:
        bus_device(servos=servos)
    assert f"devices.arm.{key}:" in str(caught.value) and words in str(caught.value)
    assert "\n" not in str(caught.value)


def test_a_feetech_bus_takes_no_current_command() -> None:
    servos = [{"name": "a", "id": 1, "model": "STS3215", "range_rad": [-1, 1]}]
    with pytest.raises(DeviceError, match=r"devices\.arm\.command: 'current'; a feetech bus takes position"):
        bus_device("feetech", servos, command="current")


# --- configure: what the servos answer ----------------------------------------------------------------

def test_an_id_not_on_the_bus_is_a_mismatch() -> None:
    with pytest.raises(DeviceMismatch, match=r"servos\[1\]\.id: servo 2 \(tilt\) is not on the bus"):
        attached(bus_device(), ids=[1])


def test_another_model_is_a_mismatch() -> None:
    with pytest.raises(DeviceMismatch, match=r"servo 1 \(pan\) is a XL430-W250 \(model number 1060\); the app "
                       r"says XM430-W350 \(1020\)"):
        attached(bus_device(), models=["XL430-W250", "XM430-W350"])


def test_a_range_outside_the_servos_limits_is_a_mismatch() -> None:
    device = bus_device()
    bus = build_bus("dynamixel", [1, 2], ["XM430-W350"], 0.002)
    bus.servos[2].set("max_position", 2500)
    with pytest.raises(DeviceMismatch, match=r"servos\[1\]\.range_rad: .* allows 0\.\.2500"):
        device.attach(ModelLine(bus))


def test_another_baud_rate_is_a_mismatch() -> None:
    device = bus_device(baudrate=57600)
    with pytest.raises(DeviceMismatch, match="is set to 1000000 baud; the app says 57600"):
        attached(device)


def test_no_servo_answering_is_not_ready() -> None:
    with pytest.raises(DeviceNotReady, match="no servo answered"):
        attached(bus_device(), ids=[7])


# --- the cycle ---------------------------------------------------------------------------------------

@pytest.mark.parametrize(("kind", "model"), [("dynamixel", "XM430-W350"), ("feetech", "STS3215")])
def test_the_servos_follow_their_goals_in_radians(kind: str, model: str) -> None:
    servos = [{**servo, "model": model} for servo in PAN_TILT]
    device = bus_device(kind, servos)
    bus = attached(device)
    y = np.zeros(device.n_outputs)
    for _ in range(400):
        device.write(np.array([0.5, -0.3]))
        device.read(y)
    assert y[0:2] == pytest.approx([0.5, -0.3], abs=0.002)  # within a tick
    assert bus.servos[2].get("goal_position") == round(2048 + 0.3 / (2 * np.pi / 4096))  # direction -1
    assert all(servo.torque_on for servo in bus.servos.values())
    device.write_safe(np.zeros(2))
    assert not any(servo.torque_on for servo in bus.servos.values())


def test_a_silent_servo_is_stale_then_a_fault() -> None:
    device = bus_device(on_missing="stale", max_stale_in_a_row=3, timeout_ms=1.0)
    attached(device, faults={2: Faults(silent_after_reads=5)})
    y = np.zeros(device.n_outputs)
    for _ in range(5):
        device.write(np.array([0.2, 0.1]))
        device.read(y)
    before = y.copy()
    for _ in range(2):
        device.write(np.array([0.2, 0.1]))
        device.read(y)
    assert y[1] == before[1] and device.stale_reads == 2  # tilt kept its last reading
    assert device.stale_sources() == {"servo 2 (tilt): no answer": 2}
    device.write(np.array([0.2, 0.1]))
    with pytest.raises(DeviceFault, match=r"servo 2 \(tilt\) did not answer the sync read .* 3 reads in a row"):
        device.read(y)


def test_a_silent_servo_is_a_fault_when_declared() -> None:
    device = bus_device(timeout_ms=1.0)
    attached(device, faults={1: Faults(silent_after_reads=0)})
    with pytest.raises(DeviceFault, match=r"servo 1 \(pan\) did not answer .* on_missing = \"stale\""):
        device.read(np.zeros(device.n_outputs))


@pytest.mark.parametrize("kind", ["dynamixel", "feetech"])
def test_a_hardware_error_is_a_fault_or_a_reading(kind: str) -> None:
    servos = [{**servo, "model": "XM430-W350" if kind == "dynamixel" else "STS3215"} for servo in PAN_TILT]
    faulting = bus_device(kind, servos)
    attached(faulting, faults={2: Faults(hardware_error_after_reads=3, hardware_error_bits=0x04)})
    y = np.zeros(faulting.n_outputs)
    for _ in range(3):
        faulting.read(y)
    with pytest.raises(DeviceFault, match=r"servo 2 \(tilt\) reports a hardware error: 0x04 \(overheat"):
        faulting.read(y)
    reporting = bus_device(kind, servos, on_hardware_error="report")
    bus = attached(reporting, faults={2: Faults(hardware_error_after_reads=3, hardware_error_bits=0x04)})
    for _ in range(5):
        reporting.read(y)
    assert y[6:8].tolist() == [0.0, 4.0]  # pan_error, tilt_error
    assert not bus.servos[2].torque_on and bus.servos[1].torque_on  # the servo turned its own torque off


def test_an_error_reading_clears_when_the_status_does() -> None:
    """Feetech's error bits are the status of the moment (a voltage dip passes): the reading follows them."""
    servos = [{**servo, "model": "STS3215"} for servo in PAN_TILT]
    device = bus_device("feetech", servos, on_hardware_error="report")
    bus = attached(device)
    y = np.zeros(device.n_outputs)
    bus.servos[1].error_bits = 0x01  # input voltage
    device.read(y)
    assert y[6:8].tolist() == [1.0, 0.0]
    bus.servos[1].error_bits = 0
    device.read(y)
    assert y[6:8].tolist() == [0.0, 0.0]


def test_the_tail_of_a_late_answer_does_not_spoil_the_next_reads() -> None:
    """The input was flushed before a request while a late answer was still on its way: its tail comes
    first. The read passes over it to the answers (it gave up at the first bad byte, and so did every
    read after it: a flush, the tail of the answer it missed, again)."""
    device = bus_device()
    bus = attached(device)
    y = np.zeros(device.n_outputs)
    device.read(y)
    late_tail = bus.receive(bytes(device.state.request))[5:]  # an answer cut by the flush
    line = device.line
    sent = line.send

    def send_after_the_tail(data: Any) -> None:
        line.pending += late_tail
        sent(data)

    line.send = send_after_the_tail
    device.read(y)
    assert device.stale_reads == 0 and not device.incomplete
