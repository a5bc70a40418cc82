"""The emulated ESC in process (no socket): datagrams, SII, AL states, FMMUs, the SM watchdog."""

from __future__ import annotations

import struct

from rtloop.io.drives import cia402
from rtloop.io.drives.drive_model import DriveModel
from rtloop.io.drives.esc import (
    AL_OP,
    AL_PREOP,
    AL_SAFEOP,
    BRD,
    BWR,
    FPRD,
    FPRW,
    FPWR,
    FRMW,
    LRW,
    EmulatedSlave,
    Segment,
)
from rtloop.io.drives.pdo import DEFAULT_RXPDO, DEFAULT_TXPDO, PdoLayout
from rtloop.io.drives.rawsocket import new_frame, put_datagram
from rtloop.io.drives.sii import Identity, parse_sii


class Clock:
    def __init__(self) -> None:
        self.ns = 0

    def __call__(self) -> int:
        return self.ns


def _segment(count: int = 2, dc: tuple[bool, ...] = ()) -> tuple[Segment, list[str], Clock]:
    log: list[str] = []
    clock = Clock()
    slaves = [EmulatedSlave(i + 1, Identity(0xA7E, 0x402402 + i, 3), PdoLayout(DEFAULT_RXPDO),
                            PdoLayout(DEFAULT_TXPDO), DriveModel(), log=log.append, clock=clock,
                            dc=dc[i] if dc else True) for i in range(count)]
    return Segment(slaves, clock), log, clock


def _one(segment: Segment, command: int, address: int, data: bytes | int) -> tuple[bytes, int, int]:
    length = data if isinstance(data, int) else len(data)
    frame = new_frame(12 + length)
    put_datagram(frame, 16, command, 7, address, length)
    if not isinstance(data, int):
        frame[26:26 + length] = data
    assert segment.process(frame)
    wkc, = struct.unpack_from("<H", frame, 26 + length)
    adp, = struct.unpack_from("<H", frame, 18)
    return bytes(frame[26:26 + length]), wkc, adp


def _fp(station: int, register: int) -> int:
    return station | register << 16


def test_a_broadcast_read_counts_every_slave_and_position_addresses_reach_each() -> None:
    segment, _, _ = _segment(3)
    _, wkc, adp = _one(segment, BRD, 0x0000, 2)
    assert wkc == 3 and adp == 3
    for position in range(3):
        _one(segment, 2, ((-position) & 0xFFFF) | 0x0010 << 16, struct.pack("<H", 0x1001 + position))  # APWR station
    data, wkc, _ = _one(segment, FPRD, _fp(0x1002, 0x0010), 2)
    assert wkc == 1 and struct.unpack("<H", data)[0] == 0x1002


def test_the_sii_reads_back_as_it_was_built() -> None:
    segment, _, _ = _segment(1)
    _one(segment, 2, 0x0010 << 16, struct.pack("<H", 0x1001))

    def read(word: int) -> bytes:
        _one(segment, FPWR, _fp(0x1001, 0x0502), struct.pack("<HI", 0x0100, word))
        return _one(segment, FPRD, _fp(0x1001, 0x0508), 8)[0]

    info = parse_sii(read)
    assert info.identity == Identity(0xA7E, 0x402402, 3)
    assert [entry.index for entry in info.rxpdo] == list(DEFAULT_RXPDO)
    assert [entry.index for entry in info.txpdo] == list(DEFAULT_TXPDO)
    assert info.name == "rtloop emulated CiA 402 drive"
    assert [sm.kind for sm in info.sync_managers] == [3, 4]
    assert info.dc_assign_activate == 0x0300  # cyclic operation and SYNC0


def test_a_slave_without_distributed_clocks_says_so_in_its_sii_and_its_esc_features() -> None:
    segment, _, _ = _segment(1, dc=(False,))
    slave = segment.slaves[0]
    _one(segment, 2, 0x0010 << 16, struct.pack("<H", 0x1001))

    def read(word: int) -> bytes:
        _one(segment, FPWR, _fp(0x1001, 0x0502), struct.pack("<HI", 0x0100, word))
        return _one(segment, FPRD, _fp(0x1001, 0x0508), 8)[0]

    assert parse_sii(read).dc_assign_activate == 0
    assert struct.unpack("<H", _one(segment, FPRD, _fp(0x1001, 0x0008), 2)[0])[0] & 0x0004 == 0
    assert slave.dc is None


def _stations(segment: Segment) -> None:
    for slave in segment.slaves:
        slave.memory[0x0010:0x0012] = struct.pack("<H", 0x1000 + slave.position)


def test_the_dc_unit_latches_receive_times_keeps_an_offset_and_starts_sync0_where_told() -> None:
    segment, log, clock = _segment(3)
    _stations(segment)
    clock.ns = 5_000_000_000
    assert struct.unpack("<H", _one(segment, FPRD, _fp(0x1001, 0x0008), 2)[0])[0] & 0x0004  # ESC feature: DC
    _, wkc, _ = _one(segment, BWR, 0x0900 << 16, 4)  # latch every slave's receive times
    assert wkc == 3
    port0 = [struct.unpack("<I", _one(segment, FPRD, _fp(0x1001 + i, 0x0900), 4)[0])[0] for i in range(3)]
    port1 = [struct.unpack("<I", _one(segment, FPRD, _fp(0x1001 + i, 0x0904), 4)[0])[0] for i in range(3)]
    local = [slave.dc.local_ns() for slave in segment.slaves if slave.dc is not None]
    assert len(set(local)) == 3  # each its own local clock
    # the frame comes back through port 1 later the more slaves stand behind: the delays a master finds
    assert [port1[i] - port0[i] for i in range(2)] == [4 * 250, 2 * 250] and port1[2] == 0
    # the offset makes every system time one: the master's (here 123 s since 2000)
    for i in range(3):
        unit_time, = struct.unpack("<Q", _one(segment, FPRD, _fp(0x1001 + i, 0x0918), 8)[0])
        _one(segment, FPWR, _fp(0x1001 + i, 0x0920), struct.pack("<Q", (123_000_000_000 - unit_time) % (1 << 64)))
    clock.ns += 1_000_000
    times = [struct.unpack("<Q", _one(segment, FPRD, _fp(0x1001 + i, 0x0910), 8)[0])[0] for i in range(3)]
    assert [t - 123_001_000_000 for t in times] == [0, -250, -500]  # (each latched later down the line)
    # the per-cycle FRMW: the reference reads its system time, the others take it (+1 each)
    data, wkc, _ = _one(segment, FRMW, _fp(0x1001, 0x0910), 8)
    assert wkc == 3 and struct.unpack("<Q", data)[0] == times[0]
    # SYNC0 at a start time and a cycle: logged as activated, then its first pulse when it comes
    start = 123_010_000_000
    _one(segment, FPWR, _fp(0x1002, 0x0990), struct.pack("<Q", start))
    _one(segment, FPWR, _fp(0x1002, 0x09A0), struct.pack("<I", 2_000_000))
    _one(segment, FPWR, _fp(0x1002, 0x0981), bytes([0x03]))
    # the start in the emulator's own clock: 10 ms after the offset was set, less slave 2's 250 ns down the line
    monotonic = 5_000_000_000 + 10_000_000 + 250
    assert f"slave 2: DC SYNC0 activated: start at system time {start} ns (CLOCK_MONOTONIC {monotonic} ns here), " \
           "cycle 2000000 ns" in log
    assert not any("first pulse" in line for line in log)
    clock.ns += 9_000_249  # 1 ns before the start on slave 2's system time
    segment.slaves[1].tick(clock.ns)
    assert not any("first pulse" in line for line in log)
    clock.ns += 1
    segment.slaves[1].tick(clock.ns)
    assert f"slave 2: DC SYNC0 first pulse at system time {start} ns (cycle 2000000 ns)" in log
    clock.ns += 3_000_000
    next_pulse, = struct.unpack("<Q", _one(segment, FPRD, _fp(0x1002, 0x0990), 8)[0])
    assert next_pulse == start + 2 * 2_000_000  # read back: the next SYNC0 pulse
    _one(segment, FPRW, _fp(0x1002, 0x0981), bytes([0x00]))
    assert "slave 2: DC SYNC0 deactivated" in log


def test_a_slave_without_dc_does_not_take_the_reference_time_nor_count_it() -> None:
    segment, _, _ = _segment(3, dc=(True, False, True))
    _stations(segment)
    _, wkc, _ = _one(segment, FRMW, _fp(0x1001, 0x0910), 8)
    assert wkc == 2


def _to_op(segment: Segment) -> None:
    for slave in segment.slaves:
        station = 0x1000 + slave.position
        slave.memory[0x0010:0x0012] = struct.pack("<H", station)
        _one(segment, FPWR, _fp(station, 0x0120), struct.pack("<H", AL_PREOP))
        rx, tx = slave.rx.size, slave.tx.size
        sms = struct.pack("<HHBBBB", 0x1000, rx, 0x64, 0, 1, 0) + struct.pack("<HHBBBB", 0x1200, tx, 0x20, 0, 1, 0)
        _one(segment, FPWR, _fp(station, 0x0800), sms)
        first = 0 if slave.position == 1 else 13
        fmmus = (struct.pack("<IHBBHBBBxxx", first, rx, 0, 7, 0x1000, 0, 2, 1)
                 + struct.pack("<IHBBHBBBxxx", 26 + (0 if slave.position == 1 else 19), tx, 0, 7, 0x1200, 0, 1, 1))
        _one(segment, FPWR, _fp(station, 0x0600), fmmus)
        _one(segment, FPWR, _fp(station, 0x0120), struct.pack("<H", AL_SAFEOP))
        _one(segment, FPWR, _fp(station, 0x0120), struct.pack("<H", AL_OP))
        assert slave.al_status == AL_OP


def test_lrw_exchanges_process_data_and_steps_each_drive_once() -> None:
    segment, log, _clock = _segment(2)
    _to_op(segment)
    outputs = struct.pack("<HbiiH", cia402.CW_SHUTDOWN, 8, 0, 0, 0)
    data, wkc, _ = _one(segment, LRW, 0, outputs + outputs + bytes(38))
    assert wkc == 6  # two slaves, each +1 read +2 write
    statusword, = struct.unpack_from("<H", data, 26)
    assert cia402.state_of(statusword) == cia402.Cia402State.SWITCH_ON_DISABLED  # inputs from before the step
    assert segment.slaves[0].drive.state == cia402.Cia402State.READY_TO_SWITCH_ON
    assert any("drive: ready to switch on" in line for line in log)


def test_a_slave_leaves_op_when_process_data_stops_for_its_watchdog_time() -> None:
    segment, log, clock = _segment(1)
    _to_op(segment)
    slave = segment.slaves[0]
    clock.ns += 50_000_000
    slave.tick(clock.ns)
    assert slave.al_status == AL_OP
    clock.ns += 60_000_000
    slave.tick(clock.ns)
    assert slave.al_status & 0x0F == AL_SAFEOP and slave.al_status & 0x10
    assert struct.unpack_from("<H", slave.memory, 0x0134)[0] == 0x001B
    assert any("left OP (SM watchdog" in line for line in log)


def test_safe_op_is_refused_with_sync_managers_that_do_not_match_the_mapping() -> None:
    segment, _log, _ = _segment(1)
    slave = segment.slaves[0]
    slave.memory[0x0010:0x0012] = struct.pack("<H", 0x1001)
    _one(segment, FPWR, _fp(0x1001, 0x0120), struct.pack("<H", AL_PREOP))
    _one(segment, FPWR, _fp(0x1001, 0x0800), struct.pack("<HHBBBB", 0x1000, 4, 0x64, 0, 1, 0))
    _one(segment, FPWR, _fp(0x1001, 0x0120), struct.pack("<H", AL_SAFEOP))
    assert slave.al_status == AL_PREOP | 0x10
    assert struct.unpack_from("<H", slave.memory, 0x0134)[0] == 0x001D


def test_a_dropped_slave_answers_nothing() -> None:
    segment, _, _ = _segment(2)
    segment.slaves[1].dropped = True
    assert _one(segment, BRD, 0x0000, 2)[1] == 1
