"""The EtherCAT device's per-cycle code through its twin (no bus): enabling, a mode change at a
release, SI readings, named faults, and no allocation that stays over 10,000 cycles."""

from __future__ import annotations

import math
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
