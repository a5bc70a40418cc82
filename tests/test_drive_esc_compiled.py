"""The emulated slaves' compiled process-data path (io/devio_c/esc_frame.c, esc_drive.c) answers as
the Python reference (io/drives/esc.py with drive_model.DriveModel) does, bit for bit: six drives,
the same frames, a few hundred cycles with mode changes, a quick stop, a following error, an
injected fault and its reset, a slave leaving OP, a mixed frame, the SM watchdog and a drop-out;
distributed clocks (the reference's time carried by an FRMW after the LRW, SYNC0 started, a slave
without DC, DC units lost)."""

from __future__ import annotations

import math
import struct

import pytest

from rtloop.io import compiled
from rtloop.io.drives import cia402
from rtloop.io.drives.drive_model import DriveModel, DriveParameters, emulated_drive
from rtloop.io.drives.esc import AL_OP, AL_PREOP, AL_SAFEOP, FPRD, FPWR, FRMW, LRW, EmulatedSlave, Segment
from rtloop.io.drives.pdo import DEFAULT_RXPDO, DEFAULT_TXPDO, PdoLayout
from rtloop.io.drives.rawsocket import new_frame, put_datagram
from rtloop.io.drives.sii import Identity

pytestmark = pytest.mark.skipif(compiled.devio() is None, reason=f"no compiled path here: {compiled.why_python()}")

DRIVES = 6
RX, TX = PdoLayout(DEFAULT_RXPDO).size, PdoLayout(DEFAULT_TXPDO).size
IMAGE = DRIVES * (RX + TX)
DRIVE_ATTRIBUTES = ("state", "mode", "theta", "omega", "torque_Nm", "rate_theta", "rate_omega", "pd_state", "pi_state",
                    "rate_pd", "rate_pi", "last_controlword", "error_code", "pending_fault", "target_position",
                    "quick_stop_done", "statusword", "mode_display", "position", "velocity", "torque",
                    "following_error")


class Clock:
    def __init__(self) -> None:
        self.ns = 0

    def __call__(self) -> int:
        return self.ns


class Side:
    """Six slaves on one segment, with the reference's drives or the compiled ones."""

    def __init__(self, use_compiled: bool) -> None:
        self.log: list[str] = []
        self.clock = Clock()
        parameters = DriveParameters(cycle_s=0.00025, following_error_window=40_000)
        self.slaves = [EmulatedSlave(i + 1, Identity(0xA7E, 0x402402, 3), PdoLayout(DEFAULT_RXPDO),
                                     PdoLayout(DEFAULT_TXPDO), emulated_drive(parameters, use_compiled),
                                     log=self.log.append, clock=self.clock, dc=i != 3) for i in range(DRIVES)]
        self.segment = Segment(self.slaves, self.clock)
        assert self.segment.compiled == use_compiled
        assert isinstance(self.slaves[0].drive, DriveModel) != use_compiled

    def send(self, frame: bytearray) -> bytes:
        assert self.segment.process(frame)
        return bytes(frame)

    def state(self) -> list[object]:
        return [(bytes(s.memory), list(s.counters[:5]), [getattr(s.drive, name) for name in DRIVE_ATTRIBUTES])
                for s in self.slaves]


def _register(command: int, station: int, register: int, data: bytes | int) -> bytearray:
    length = data if isinstance(data, int) else len(data)
    frame = new_frame(12 + length)
    put_datagram(frame, 16, command, 7, station | register << 16, length)
    if not isinstance(data, int):
        frame[26:26 + length] = data
    return frame


def configuration_frames() -> list[bytearray]:
    """What a master writes to take each slave to OP, the process image laid out slave after slave."""
    frames = []
    for k in range(DRIVES):
        station = 0x1001 + k
        frames.append(_register(2, (-k) & 0xFFFF, 0x0010, struct.pack("<H", station)))  # APWR station address
        frames.append(_register(FPWR, station, 0x0120, struct.pack("<H", AL_PREOP)))
        frames.append(_register(FPWR, station, 0x0800, struct.pack("<HHBBBB", 0x1000, RX, 0x64, 0, 1, 0) +
                                struct.pack("<HHBBBB", 0x1200, TX, 0x20, 0, 1, 0)))
        frames.append(_register(FPWR, station, 0x0600, struct.pack("<IHBBHBBBxxx", k * RX, RX, 0, 7, 0x1000, 0, 2, 1) +
                                struct.pack("<IHBBHBBBxxx", DRIVES * RX + k * TX, TX, 0, 7, 0x1200, 0, 1, 1)))
        frames.append(_register(FPWR, station, 0x0920, struct.pack("<Q", (-1_000_000_007 * (k + 1)) & (2**64 - 1))))
        frames.append(_register(FPWR, station, 0x0928, struct.pack("<I", 500 * k)))  # system time offset and delay
        frames.append(_register(FPWR, station, 0x0120, struct.pack("<H", AL_SAFEOP)))
        frames.append(_register(FPWR, station, 0x0120, struct.pack("<H", AL_OP)))
    return frames


def _outputs(cycle: int, joint: int) -> tuple[int, int, int, int, int]:
    """The command sequence: (controlword, mode, target position, velocity, torque) of a joint."""
    enabling = (0, 6, 7, 0x0F)
    controlword = enabling[min(cycle // 3, 3)]
    mode, position, velocity, torque = 8, round(3000 * math.sin(cycle / 40) * (joint + 1)), 0, 0
    if joint == 2 and cycle >= 60:
        mode, velocity = 9, 400 if cycle < 200 else -900
    if joint == 3 and cycle >= 70:
        mode, torque = 10, 120 if cycle < 150 else 3000  # 3000 ‰: beyond the torque limit, the warning bit
    if joint == 4 and cycle >= 120:
        position = 100_000 if cycle < 220 else 0  # a following error beyond the window: fault, then reset
        if cycle >= 220:
            controlword = (0x80, 0, 6, 7, 0x0F)[min((cycle - 220) // 3, 4)]
    if joint < 4 and 250 <= cycle < 280:
        controlword = 0x02  # quick stop
    elif joint < 4 and cycle >= 280:
        controlword = (6, 7, 0x0F)[min((cycle - 280) // 3, 2)]
    return controlword, mode, position, velocity, torque


def cycle_frame(cycle: int, before: bytes = b"") -> bytearray:
    """The cycle's frame: (a register datagram,) the LRW, the FRMW of slave 1's system time."""
    frame = new_frame(len(before) + 12 + IMAGE + 12 + 8)
    at = 16
    if before:
        frame[at:at + len(before)] = before
        struct.pack_into("<H", frame, at + 6, struct.unpack_from("<H", frame, at + 6)[0] | 0x8000)  # more follow
        at += len(before)
    put_datagram(frame, at, LRW, 0, 0, IMAGE, more=True)
    put_datagram(frame, at + 12 + IMAGE, FRMW, 1, 0x1001 | 0x0910 << 16, 8)
    for joint in range(DRIVES):
        struct.pack_into("<HbiiH", frame, at + 10 + joint * RX, *_outputs(cycle, joint))
    return frame


def test_the_compiled_path_answers_every_frame_as_the_reference_does() -> None:
    reference, fast = Side(False), Side(True)
    for frame in configuration_frames():
        assert reference.send(bytearray(frame)) == fast.send(bytearray(frame))
    assert all(slave.al_status == AL_OP for slave in fast.slaves)
    status_frame = _register(FPRD, 0x1001, 0x0130, 2)[16:28]  # a register datagram before the LRW: the reference's
    faults = {150: lambda side: side.slaves[5].drive.inject_fault(),
              330: lambda side: side.send(_register(FPWR, 0x1002, 0x0120, struct.pack("<H", AL_SAFEOP))),
              100: lambda side: side.send(_sync0(side.clock.ns)),
              200: lambda side: setattr(side.slaves[1], "dc", None),  # a DC unit lost: no time written
              380: lambda side: setattr(side.slaves[0], "dropped", True),
              400: lambda side: setattr(side.slaves[2], "dc", None)}
    readings = []
    for cycle in range(420):
        for side in (reference, fast):
            side.clock.ns += 250_000
            if cycle in faults:
                faults[cycle](side)
            if cycle == 360:  # the master stalls for 200 ms: the SM watchdog takes the slaves out of OP
                side.clock.ns += 200_000_000
            side.segment.tick(side.clock.ns)
        frame = cycle_frame(cycle, bytes(status_frame) if cycle % 50 == 7 else b"")
        answer = reference.send(bytearray(frame))
        assert fast.send(bytearray(frame)) == answer, f"cycle {cycle}: the answers differ"
        assert fast.state() == reference.state(), f"cycle {cycle}: the slaves differ"
        assert fast.log == reference.log, f"cycle {cycle}: the logs differ"
        readings.append(answer)
    text = "\n".join(reference.log)
    for event in ("operation enabled (csp)", "mode csp -> csv", "mode csp -> cst", "fault 0x8611: following error",
                  "fault reset", "quick stop (controlword)", "quick stop done: at rest", "fault 0x5530",
                  "slave 2: left OP", "SM watchdog", "fault (error code 0x5530), drive at rest",
                  "slave 3: DC SYNC0 activated", "slave 3: DC SYNC0 first pulse"):
        assert event in text, event  # the sequence went through what it is meant to show
    statuswords = {struct.unpack_from("<H", answer, 26 + DRIVES * RX + 3 * TX)[0] for answer in readings}
    assert any(word & cia402.StatusBits.WARNING for word in statuswords)  # the CST joint at its torque limit
    assert len(set(readings)) > 400  # the readings moved


def _sync0(now_ns: int) -> bytearray:
    """SYNC0 of slave 3 started 2 ms ahead in its system time, cycling at 250 µs."""
    start = now_ns + 2_000_000  # its system time is CLOCK_MONOTONIC: the offset above took its local start out
    frame = new_frame(12 + 8 + 12 + 4 + 12 + 1)
    second = put_datagram(frame, 16, FPWR, 1, 0x1003 | 0x0990 << 16, 8, more=True)
    struct.pack_into("<Q", frame, 26, start)
    third = put_datagram(frame, second, FPWR, 2, 0x1003 | 0x09A0 << 16, 4, more=True)
    struct.pack_into("<I", frame, second + 10, 250_000)
    put_datagram(frame, third, FPWR, 3, 0x1003 | 0x0981 << 16, 1)
    frame[third + 10] = 0x03
    return frame


def test_the_compiled_drive_is_the_reference_for_arbitrary_commands() -> None:
    reference, fast = DriveModel(), emulated_drive()
    assert not isinstance(fast, DriveModel)
    commands = [(0x06, 8, 0, 0, 0), (0x07, 8, 0, 0, 0), (0x0F, 8, 5000, 0, 0), (0x0F, 9, 0, -70000, 0),
                (0x0F, 10, 0, 0, -2000), (0x0F, 12, 0, 0, 0), (0x0B, 10, 0, 0, 0), (0x00, 8, 0, 0, 0)]
    for step in range(800):
        command = commands[step // 100]
        valid = step not in (5, 750)  # outputs not valid (the slave out of OP) now and then
        reference.exchange(*command, outputs_valid=valid)
        fast.exchange(*command, outputs_valid=valid)
        assert [getattr(fast, name) for name in DRIVE_ATTRIBUTES] == \
            [getattr(reference, name) for name in DRIVE_ATTRIBUTES], f"step {step}"
        assert fast.events == reference.events
    assert "mode csv -> cst" in reference.events and "quick stop (controlword)" in reference.events


def test_a_mapping_the_compiled_path_does_not_take_is_served_by_python() -> None:
    tx = PdoLayout(DEFAULT_TXPDO * 3)  # 21 inputs: more than the compiled path's 16
    slave = EmulatedSlave(1, Identity(0xA7E, 0x402402, 3), PdoLayout(DEFAULT_RXPDO), tx, emulated_drive())
    segment = Segment([slave])
    assert not segment.compiled
    assert segment.process(_register(FPRD, 0, 0x0130, 2))
