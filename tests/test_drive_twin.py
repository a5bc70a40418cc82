"""The EtherCAT device's per-cycle code through its twin (no bus): enabling, a mode change at a
release, SI readings, named faults, and no allocation that stays over 10,000 cycles."""

from __future__ import annotations

import math
import socket
import struct
import tracemalloc

import numpy as np
import pytest

from rtloop.errors import DeviceFault
from rtloop.io.device import build_device
from rtloop.io.drives.emulator import DEFAULT_IDENTITY

JOINT = {"vendor": DEFAULT_IDENTITY.vendor, "product": DEFAULT_IDENTITY.product, "revision": DEFAULT_IDENTITY.revision,
         "counts_per_rev": 4096, "gear_ratio": 10.0}


def _twin(**joint: object):  # type: ignore[no-untyped-def]
    device = build_device("ethercat", "arm", {"interface": "ecm0", "joints": [{"name": "a", **JOINT, **joint}]}, "t")
    twin = device.default_twin()
    twin.prerun()
    return device, twin


def _index(names: tuple[str, ...] | None, name: str) -> int:
    assert names is not None
    return names.index(name)


def test_the_drive_is_enabled_then_follows_and_a_mode_change_takes_effect_at_its_release() -> None:
    device, twin = _twin(modes=["csp", "csv"])
    assert device.input_names == ("a_target_position_rad", "a_target_velocity_rad_s", "a_target_mode")
    u, y = np.zeros(device.n_inputs), np.zeros(device.n_outputs)
    enabled, mode = _index(device.output_names, "a_enabled"), _index(device.output_names, "a_mode")
    position, velocity = _index(device.output_names, "a_position_rad"), _index(device.output_names, "a_velocity_rad_s")
    u[2] = 8
    cycles = 0
    while y[enabled] != 1.0:
        twin.step(u, y)
        cycles += 1
    # shutdown, switch on, enable operation; each asked twice: an answer holds the drive's inputs from
    # before its step, so a transition shows one exchange after the controlword that made it
    assert cycles == 7
    u[0] = 0.1
    for _ in range(1500):
        twin.step(u, y)
    assert math.isclose(y[position], 0.1, abs_tol=2 * 2 * math.pi / (4096 * 10))
    u[1], u[2] = 0.5, 9  # CSV from this release on
    twin.step(u, y)
    assert y[mode] == 8  # the answer to this exchange holds what the drive showed when the frame passed
    twin.step(u, y)
    assert y[mode] == 9
    for _ in range(1500):
        twin.step(u, y)
    assert math.isclose(y[velocity], 0.5, rel_tol=0.05)


def test_a_mode_the_joint_does_not_declare_is_a_named_fault() -> None:
    device, twin = _twin(modes=["csp", "csv"])
    u, y = np.zeros(device.n_inputs), np.zeros(device.n_outputs)
    u[2] = 10
    with pytest.raises(DeviceFault, match=r"joint 'a' \(slave 1.*mode command 10.0 is not one of the joint's modes"):
        twin.step(u, y)


def test_a_drive_fault_is_named_with_its_statusword_and_error_code() -> None:
    device, twin = _twin(mode="csp")
    u, y = np.zeros(device.n_inputs), np.zeros(device.n_outputs)
    for _ in range(10):
        twin.step(u, y)
    twin.drives[0].inject_fault()
    with pytest.raises(DeviceFault, match=r"drive fault: statusword 0x02.. \(0x6041: fault( reaction active)?\), "
                                          r"error code 0x5530 \(0x603F\), exchange 1[12]"):
        for _ in range(3):
            twin.step(u, y)


def test_the_cycle_keeps_nothing_it_allocates_over_10000_cycles() -> None:
    device, twin = _twin(mode="csp")
    u, y = np.zeros(device.n_inputs), np.zeros(device.n_outputs)
    for k in range(200):
        u[0] = 1e-4 * k
        twin.step(u, y)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for k in range(10_000):
        u[0] = 0.02 + 1e-6 * k
        twin.step(u, y)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    kept = [stat for stat in after.compare_to(before, "filename")
            if stat.size_diff > 0 and "drives/cycle.py" in str(stat.traceback)]
    # the last values in place of the first ones (a few ints), never a growth with the cycles
    assert sum(stat.size_diff for stat in kept) <= 256, kept


def _trajectory(monkeypatch: pytest.MonkeyPatch, pure: bool) -> np.ndarray:
    monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1" if pure else "0")
    device, twin = _twin(modes=["csp", "csv", "cst"], direction=-1)
    u, y = np.zeros(device.n_inputs), np.zeros(device.n_outputs)
    rows = []
    u[3] = 8
    for k in range(3000):
        u[0] = 0.3 * math.sin(k * 0.003) + 1e-7 * k
        u[1] = 2.0 * math.cos(k * 0.002)
        u[2] = 0.01 * math.sin(k * 0.01)
        u[3] = (8, 9, 10, 8)[(k // 700) % 4]  # mode changes at releases
        twin.step(u, y)
        rows.append(y.copy())
    assert (twin.cycle._fast is None) == pure  # the C cycle ran where it was asked for
    return np.array(rows)


def test_the_compiled_cycle_equals_the_python_reference_bit_for_bit(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("rtloop.io._devio")
    compiled, reference = _trajectory(monkeypatch, False), _trajectory(monkeypatch, True)
    assert compiled.tobytes() == reference.tobytes()
    assert np.ptp(compiled[:, 0]) > 0.1  # never vacuous: the joint moved


def _linked(monkeypatch: pytest.MonkeyPatch, pure: bool):  # type: ignore[no-untyped-def]
    """A device bound to one end of a socket pair (its frame, its cycle; no bus), its twin's drives
    answering on the other end as the emulated slaves do, and a second twin stepping alone."""
    from rtloop.io.drives.cycle import DriveCycle

    monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1" if pure else "0")
    settings = {"interface": "ecm0", "timeout_us": 200_000, "joints": [{"name": "a", **JOINT, "mode": "csp"}]}
    device = build_device("ethercat", "arm", settings, "t")
    mine, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    mine.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, struct.pack("@ll", 0, 1))  # as open_raw: one tick
    device._expected_wkc = 3
    device._bind(DriveCycle("arm", device.joints), mine)
    slaves, alone = device.default_twin(), device.default_twin()
    slaves.prerun()
    alone.prerun()
    return device, slaves, alone, peer


def _answer(device, slaves, peer, wkc: int = 3, index_delta: int = 0) -> None:  # type: ignore[no-untyped-def]
    frame = bytearray(peer.recv(2048))
    outputs = slaves.cycle.output_bytes
    slaves.outputs[:] = frame[26:26 + outputs]
    slaves._exchange()  # the inputs the drives hold as the frame passes, then their step
    frame[26 + outputs:26 + outputs + len(slaves.inputs)] = slaves.inputs
    frame[17] = (frame[17] + index_delta) & 0xFF
    struct.pack_into("<H", frame, device._wkc_at, wkc)
    peer.send(frame)


@pytest.mark.parametrize("pure", [False, True])
def test_the_frame_exchanged_on_a_socket_equals_the_twin_and_names_what_goes_wrong(
        monkeypatch: pytest.MonkeyPatch, pure: bool) -> None:
    if not pure:
        pytest.importorskip("rtloop.io._devio")
    device, slaves, alone, peer = _linked(monkeypatch, pure)
    u, y, y_alone = np.zeros(device.n_inputs), np.zeros(device.n_outputs), np.zeros(device.n_outputs)
    moved = 0.0
    for k in range(300):
        u[0] = 0.2 * math.sin(k * 0.02)
        device.write(u)
        device._send_outputs()
        if k == 150:  # a late answer of an earlier frame is passed over
            peer.send(bytes(device._frame[:17]) + bytes([(device._frame[17] - 1) & 0xFF]) + bytes(device._frame[18:]))
        _answer(device, slaves, peer)
        device._take_answer(y)
        alone.step(u, y_alone)
        assert y.tobytes() == y_alone.tobytes(), k
        moved = max(moved, abs(y[0]))
    assert device.cycle.enabled and moved > 0.05  # never vacuous: the joint followed its target
    assert (device.cycle._fast is None) == pure and (pure or device.cycle.linked_sent_at() > 0)  # C ran, or not
    device.write(u)
    device._send_outputs()
    _answer(device, slaves, peer, wkc=1)
    with pytest.raises(DeviceFault, match=r"working counter 1, expected 3 .*not answering: joint 'a' \(slave 1\)"):
        device._take_answer(y)
    device.write(u)
    device._send_outputs()
    _answer(device, slaves, peer, index_delta=-1)  # only an answer to another frame: none to this one
    with pytest.raises(DeviceFault, match=r"the LRW frame did not come back within 200000 µs"):
        device._take_answer(y)
    device.socket.close()
    peer.close()
