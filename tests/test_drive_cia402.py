"""The CiA 402 core: statusword decoding, the master's state machine against the emulated drive,
units, and the drive model's faults, quick stop and modes (no bus: pure Python)."""

from __future__ import annotations

import math
import tracemalloc

import pytest

from io_guest_devices import bytes_grown
from rtloop.io.drives import cia402
from rtloop.io.drives.cia402 import Cia402State, JointScale, JointStateMachine, StatusBits, state_of, to_raw
from rtloop.io.drives.drive_model import FOLLOWING_ERROR_CODE, INJECTED_FAULT_CODE, DriveModel, DriveParameters


@pytest.mark.parametrize(("statusword", "state"), [
    (0x0000, Cia402State.NOT_READY_TO_SWITCH_ON), (0x0250, Cia402State.SWITCH_ON_DISABLED),
    (0x0231, Cia402State.READY_TO_SWITCH_ON), (0x0233, Cia402State.SWITCHED_ON),
    (0x1637, Cia402State.OPERATION_ENABLED), (0x0217, Cia402State.QUICK_STOP_ACTIVE),
    (0x021F, Cia402State.FAULT_REACTION_ACTIVE), (0x0218, Cia402State.FAULT),
])
def test_statusword_decodes_to_the_state_the_standard_says(statusword: int, state: Cia402State) -> None:
    assert state_of(statusword) == state


def _enable(drive: DriveModel, machine: JointStateMachine, limit: int = 20) -> int:
    for exchange in range(limit):
        word = machine.enabling_controlword(drive.statusword)
        if word == -1:
            return exchange
        assert word >= 0
        drive.exchange(word, 8, drive.position, 0, 0)
    raise AssertionError("not enabled")


def test_the_master_enables_a_drive_one_transition_per_exchange() -> None:
    drive, machine = DriveModel(), JointStateMachine()
    assert state_of(drive.statusword) == Cia402State.SWITCH_ON_DISABLED
    assert _enable(drive, machine) == 3  # shutdown, switch on, enable operation
    assert drive.events == ["ready to switch on", "switched on", "operation enabled (csp)"]


def test_a_fault_is_reset_on_a_rising_edge_then_the_drive_is_enabled() -> None:
    drive, machine = DriveModel(), JointStateMachine()
    _enable(drive, machine)
    drive.inject_fault()
    for _ in range(50):
        drive.exchange(cia402.CW_ENABLE_OPERATION, 8, drive.position, 0, 0)
    assert state_of(drive.statusword) == Cia402State.FAULT
    assert drive.error_code == INJECTED_FAULT_CODE
    assert drive.statusword & StatusBits.FAULT
    words = []
    for _ in range(10):
        word = machine.enabling_controlword(drive.statusword)
        if word == -1:
            break
        words.append(word)
        drive.exchange(word, 8, drive.position, 0, 0)
    assert words[0] == cia402.CW_FAULT_RESET
    assert state_of(drive.statusword) == Cia402State.OPERATION_ENABLED
    assert drive.error_code == 0


def test_a_fault_that_does_not_reset_is_given_up_after_a_few_edges() -> None:
    machine = JointStateMachine()
    words = [machine.enabling_controlword(0x0218) for _ in range(40)]
    assert -2 in words
    assert words.count(cia402.CW_FAULT_RESET) == JointStateMachine.FAULT_RESET_TRIES


def test_the_safe_transition_is_quick_stop_until_at_rest_then_disable() -> None:
    drive, machine = DriveModel(DriveParameters(quick_stop_torque_Nm=0.05)), JointStateMachine()
    _enable(drive, machine)
    for _ in range(200):  # spin it up in CSV
        drive.exchange(cia402.CW_ENABLE_OPERATION, 9, 0, 40_000, 0)
    assert drive.velocity > 10_000
    drive.events.clear()
    words = []
    for _ in range(2000):
        word = machine.stopping_controlword(drive.statusword)
        if word == -1:
            break
        words.append(word)
        drive.exchange(word, 9, 0, 40_000, 0)
    assert words[0] == cia402.CW_QUICK_STOP
    assert words[-1] == cia402.CW_DISABLE_VOLTAGE
    assert words.count(cia402.CW_QUICK_STOP) > 5  # it braked over several cycles before the voltage went
    assert drive.events[0] == "quick stop (controlword)"
    assert "quick stop done: at rest" in drive.events
    assert state_of(drive.statusword) == Cia402State.SWITCH_ON_DISABLED
    assert abs(drive.velocity) < 50


def test_csp_follows_and_a_runaway_target_is_a_following_error_fault() -> None:
    drive = DriveModel(DriveParameters(following_error_window=20_000))
    machine = JointStateMachine()
    _enable(drive, machine)
    for _ in range(2000):
        drive.exchange(cia402.CW_ENABLE_OPERATION, 8, 1000, 0, 0)
    assert abs(drive.position - 1000) < 30
    drive.exchange(cia402.CW_ENABLE_OPERATION, 8, 10_000_000, 0, 0)
    for _ in range(200):
        drive.exchange(cia402.CW_ENABLE_OPERATION, 8, 10_000_000, 0, 0)
    assert drive.error_code == FOLLOWING_ERROR_CODE
    assert state_of(drive.statusword) in (Cia402State.FAULT, Cia402State.FAULT_REACTION_ACTIVE)


def test_a_mode_change_takes_effect_at_the_exchange_and_an_unsupported_mode_is_not_taken() -> None:
    drive = DriveModel(DriveParameters(modes=(8, 9)))
    _enable(drive, JointStateMachine())
    drive.exchange(cia402.CW_ENABLE_OPERATION, 9, 0, 1000, 0)
    assert drive.mode_display == 9
    drive.exchange(cia402.CW_ENABLE_OPERATION, 10, 0, 0, 100)
    assert drive.mode_display == 9


def test_units_counts_gear_and_direction() -> None:
    scale = JointScale(counts_per_rev=4096, gear_ratio=19.0, direction=-1, rated_torque_Nm=0.2)
    assert scale.problem() is None
    assert math.isclose(4096 * 19 * scale.rad_per_count, -2 * math.pi)
    assert to_raw(-2 * math.pi, scale.rad_per_count, 32) == 4096 * 19
    assert to_raw(1e30, scale.rad_per_count, 32) == -(1 << 31)  # saturated, not wrapped
    assert math.isclose(1000 * scale.Nm_per_permille, -0.2 * 19)
    assert JointScale(counts_per_rev=0).problem()
    assert JointScale(counts_per_rev=10, direction=2).problem()


def test_the_state_machine_and_the_model_allocate_nothing_per_exchange() -> None:
    drive, machine = DriveModel(), JointStateMachine()
    _enable(drive, machine)
    drive.events.clear()

    def cycles(count: int) -> None:
        for k in range(count):
            machine.running_controlword()
            state_of(drive.statusword)
            drive.exchange(cia402.CW_ENABLE_OPERATION, 8, k, 0, 0)

    cycles(100)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    cycles(10_000)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = bytes_grown(before, after)
    assert grown < 2048, grown
