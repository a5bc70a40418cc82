"""The servo packets' CRC-16 (Dynamixel 2.0) and checksum (Feetech) in C (``io/devio_c/servo.c``) are their
Python references' (``io/servos/protocol.py``) bit for bit: on the protocol documents' example packets, on
random bytes, on whole packets scanned and sealed; the running cycle uses them; and a cycle of six servos
keeps nothing allocated over 10,000 cycles (the references: 1,000)."""

from __future__ import annotations

import random
import tracemalloc
from typing import Any

import numpy as np
import pytest

from rtloop.io.servos import protocol as reference
from rtloop.io.servos.protocol import BAD, NEED_MORE, PROTOCOLS, Checks, Dynamixel2, Feetech, Scan, for_the_cycle
from servo_lines import servos_answering_at_once

devio = pytest.importorskip("rtloop.io._devio", reason="the devices' C part was not built (no compiler)")
COMPILED = Checks(devio)
PYTHON = Checks()

# Packets as printed in the ROBOTIS e-manual's Protocol 2.0 page (instruction and status examples; the
# last two bytes are the CRC, low byte first) and its Protocol 1.0 page (Feetech's frame; the last byte is
# the checksum). Facts to check against, no code.
DYNAMIXEL_EXAMPLES = [
    "FF FF FD 00 01 03 00 01 19 4E",  # ping ID 1
    "FF FF FD 00 01 07 00 55 00 06 04 26 65 5D",  # its status: model 1030, firmware 38
    "FF FF FD 00 FE 03 00 01 31 42",  # broadcast ping
    "FF FF FD 00 01 07 00 02 84 00 04 00 1D 15",  # read 4 bytes at 132 (present position)
    "FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0",  # its status: 166
    "FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89",  # write 512 at 116 (goal position)
    "FF FF FD 00 01 04 00 55 00 A1 0C",  # its status
    "FF FF FD 00 01 04 00 06 01 A1 E6",  # factory reset
    "FF FF FD 00 01 03 00 08 2F 4E",  # reboot
    "FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA",  # sync read 4 bytes at 132 of IDs 1, 2
    "FF FF FD 00 FE 11 00 83 74 00 04 00 01 96 00 00 00 02 AA 00 00 00 82 87",  # sync write 150 / 170 at 116
]
FEETECH_EXAMPLES = [
    "FF FF 01 02 01 FB",  # ping ID 1
    "FF FF 01 04 02 2B 01 CC",  # read 1 byte at 0x2B
    "FF FF 01 03 00 20 DB",  # its status: 32
    "FF FF FE 04 03 03 01 F6",  # broadcast write of ID 1
]


def _bytes(text: str) -> bytearray:
    return bytearray.fromhex(text)


@pytest.mark.parametrize("checks", [COMPILED, PYTHON], ids=["compiled", "python"])
def test_the_documented_packets_check_and_seal_to_their_own_bytes(checks: Checks) -> None:
    assert checks.crc16(b"123456789", 0, 9, 0) == 0xFEE8  # CRC-16/UMTS's check value
    for text in DYNAMIXEL_EXAMPLES:
        packet = _bytes(text)
        assert checks.crc_matches(packet, 0, len(packet) - 2), text
        blank = packet[:-2] + b"\0\0"
        checks.seal_crc(blank, 0, len(blank) - 2, 0)
        assert blank == packet, text
        assert bytes(PROTOCOLS["dynamixel"].packet(packet[4], packet[7], bytes(packet[8:-2]))) == packet, text
    for text in FEETECH_EXAMPLES:
        packet = _bytes(text)
        assert checks.sum_matches(packet, 2, len(packet) - 1), text
        blank = packet[:-1] + b"\0"
        checks.seal_sum(blank, 2, len(blank) - 1, 0)
        assert blank == packet, text
    broken = _bytes(DYNAMIXEL_EXAMPLES[0])
    broken[5] ^= 0x10
    assert not checks.crc_matches(broken, 0, len(broken) - 2)
    broken = _bytes(FEETECH_EXAMPLES[0])
    broken[4] ^= 0x01
    assert not checks.sum_matches(broken, 2, len(broken) - 1)


def test_random_bytes_give_the_same_crc_checksum_and_verdicts_bit_for_bit() -> None:
    generator = random.Random(32)
    for _ in range(3_000):
        size = generator.randrange(0, 300)
        data = bytearray(generator.randbytes(size + 3))
        start = generator.randrange(0, size + 1)
        end = generator.randrange(start, size + 1)
        crc = generator.randrange(0, 0x10000)
        total = generator.choice([0, generator.randrange(0, 1 << 20)])
        assert COMPILED.crc16(data, start, end, crc) == reference.crc16(data, start, end, crc)
        assert COMPILED.crc_matches(data, start, end) is reference.crc_matches(data, start, end)
        assert COMPILED.sum_matches(data, start, end) is reference.sum_matches(data, start, end)
        ours, theirs = bytearray(data), bytearray(data)
        COMPILED.seal_crc(ours, start, end, crc)
        reference.seal_crc(theirs, start, end, crc)
        assert ours == theirs
        assert reference.crc_matches(ours, start, end) is (crc == 0)  # as sealed (from the bytes before: 0)
        COMPILED.seal_sum(ours, start, end, total)
        reference.seal_sum(theirs, start, end, total)
        assert ours == theirs
        assert reference.sum_matches(ours, start, end) is (total % 256 == 0)
        view = memoryview(ours)  # the cycle hands over memoryviews and bytes as well
        assert COMPILED.crc16(view, start, end, 0) == reference.crc16(bytes(ours), start, end, 0)


def test_out_of_range_and_read_only_are_refused_not_read_past() -> None:
    with pytest.raises(IndexError):
        COMPILED.crc_matches(bytearray(10), 0, 9)  # the CRC's two bytes would be past the end
    with pytest.raises(IndexError):
        COMPILED.sum_matches(bytearray(4), 3, 2)
    with pytest.raises(IndexError):
        COMPILED.seal_sum(bytearray(4), 0, 4, 0)
    with pytest.raises(ValueError):
        COMPILED.seal_crc(bytearray(4), 0, 2, 0x10000)
    with pytest.raises(BufferError):
        COMPILED.seal_crc(b"\0\0\0\0", 0, 2, 0)  # bytes cannot be written
    with pytest.raises(TypeError):
        COMPILED.crc16(b"\0\0\0\0", 0, 2)


def _random_packets(protocol: Any, generator: random.Random) -> bytearray:
    stream = bytearray()
    for _ in range(generator.randrange(1, 6)):
        params = generator.randbytes(generator.randrange(0, 24))
        if generator.random() < 0.3:
            params += b"\xff\xff\xfd"  # Dynamixel stuffs it
        servo_id = generator.randrange(0, 253)
        if generator.random() < 0.5:
            stream += protocol.status(servo_id, generator.randrange(0, 256), params)
        else:
            stream += protocol.packet(servo_id, generator.randrange(0, 256), params)
    return stream


@pytest.mark.parametrize("kind", [Dynamixel2, Feetech], ids=["dynamixel", "feetech"])
def test_packets_scanned_with_either_give_the_same_results(kind: type) -> None:
    """Whole packets, some with one byte changed, scanned as the cycle does: the same sizes, verdicts, fields."""
    ours, theirs = kind(COMPILED), kind(PYTHON)
    generator = random.Random(7)
    results = {BAD: 0, NEED_MORE: 0, "good": 0}
    for _ in range(600):
        stream = _random_packets(theirs, generator)
        if generator.random() < 0.5:
            stream[generator.randrange(len(stream))] ^= 1 << generator.randrange(8)
        for status in (True, False):
            start = 0
            while start < len(stream):
                found = []
                for protocol in (ours, theirs):
                    scan = Scan()
                    size = protocol.scan(stream, start, len(stream), scan, status)
                    found.append((size, scan.servo_id, scan.instruction, scan.error, scan.first, scan.end,
                                  scan.needed, scan.problem))
                assert found[0] == found[1], (bytes(stream).hex(), start)
                size = found[0][0]
                results[size if size in (BAD, NEED_MORE) else "good"] += 1
                if size == NEED_MORE:
                    break
                start += 1 if size == BAD else size
    assert min(results.values()) > 0, results  # every outcome was met


@pytest.mark.parametrize("kind", ["dynamixel", "feetech"])
def test_sync_writes_sealed_with_either_are_the_same_bytes(kind: str) -> None:
    from rtloop.io.servos.protocol import SyncWrite
    from rtloop.io.servos.tables import FAMILIES

    family = FAMILIES[kind]
    field = family.fields[family.goals["position"]]
    ids = [1, 2, 3, 4, 5, 6]
    ours, theirs = SyncWrite(type(PROTOCOLS[kind])(COMPILED), field, ids), SyncWrite(PROTOCOLS[kind], field, ids)
    generator = np.random.default_rng(3)
    for _ in range(500):
        raw = np.rint(generator.uniform(-3000, 4095, 6))
        if kind == "dynamixel" and generator.random() < 0.2:
            raw[2] = float(0xFDFFFF)  # FF FF FD in the values: the stuffed packet
        ours.values.encode(raw)
        theirs.values.encode(raw)
        assert bytes(ours.seal()) == bytes(theirs.seal())


class _Chunks:
    """A line handing over ``stream`` in the given chunk sizes, then nothing (a timeout)."""

    def __init__(self, stream: bytes, sizes: list[int]) -> None:
        self.stream, self.sizes, self.at = stream, list(sizes), 0

    def send(self, data: Any) -> None:
        pass

    def receive(self, buffer: memoryview, timeout_ns: int) -> int:
        if self.at >= len(self.stream):
            return 0
        size = min(len(buffer), self.sizes.pop(0) if self.sizes else len(self.stream), len(self.stream) - self.at)
        buffer[:size] = self.stream[self.at:self.at + size]
        self.at += size
        return size

    def flush_input(self) -> None:
        pass


def _not_statuses(kind: str, servo_id: int) -> list[bytes]:
    protocol = PROTOCOLS[kind]
    if kind == "dynamixel":  # a status too short for its error byte; an instruction
        return [bytes(protocol.packet(servo_id, 0x55, b"")),
                bytes(protocol.packet(servo_id, 0x02, b"\x84\x00\x04\x00"))]
    short = bytearray([0xFF, 0xFF, servo_id, 0x01, 0x00])  # a length of 1: shorter than the error byte allows
    short[-1] = ~sum(short[2:-1]) & 0xFF
    return [bytes(short)]


@pytest.mark.parametrize("kind", ["dynamixel", "feetech"])
def test_a_sync_reads_answers_taken_in_c_are_the_loops_in_python(kind: str) -> None:
    """SyncRead.collect with its scanning loop in C (servo_take_answers) against the Python loop, on answers
    that come whole, cut in pieces, late, twice, from other IDs, of other lengths, stuffed, with a bit flipped,
    after noise, or too long for the buffer: the same servos taken, bytes, counts and problems."""
    from rtloop.io.servos.protocol import SyncRead
    from rtloop.io.servos.tables import FAMILIES

    first, width = FAMILIES[kind].state_range()
    python = PROTOCOLS[kind]
    generator = random.Random(11)
    outcomes: dict[str, int] = {}
    for _ in range(800):
        ids = generator.sample(range(0, 12), generator.randrange(1, 7))
        ours = SyncRead(type(python)(COMPILED), first, width, ids)
        theirs = SyncRead(python, first, width, ids)
        assert ours.take is not None and theirs.take is None
        stream = bytearray(generator.randbytes(generator.choice([0, 0, 1, 5])))  # noise before
        for _ in range(generator.randrange(0, len(ids) + 3)):
            servo_id = generator.choice([*ids, generator.randrange(0, 253)])
            data = bytearray(generator.randbytes(width if generator.random() < 0.85 else generator.randrange(0, 30)))
            if generator.random() < 0.2 and len(data) >= 3:
                at = generator.randrange(len(data) - 2)
                data[at:at + 3] = b"\xff\xff\xfd"  # stuffed on the wire by Dynamixel
            stream += python.status(servo_id, generator.choice([0, 0, 0x80, 0x20]), bytes(data))
            if generator.random() < 0.1:  # whole, its CRC or checksum good, yet no status of a servo
                stream += generator.choice(_not_statuses(kind, servo_id))
        if stream and generator.random() < 0.3:
            stream[generator.randrange(len(stream))] ^= 1 << generator.randrange(8)
        if generator.random() < 0.05:
            stream += bytes(len(ours.raw))  # more than the buffer holds
        sizes = [generator.randrange(1, 40) for _ in range(60)]
        start_bytes = generator.randbytes(len(ours.clean))
        ours.clean[:], theirs.clean[:] = start_bytes, start_bytes
        counts = [read.collect(_Chunks(bytes(stream), sizes), 10**9) for read in (ours, theirs)]
        assert counts[0] == counts[1], bytes(stream).hex()
        assert ours.problem == theirs.problem, bytes(stream).hex()
        assert ours.received.tolist() == theirs.received.tolist() and ours.clean == theirs.clean, bytes(stream).hex()
        outcome = f"{counts[0] == len(ids)}:{ours.problem}"
        outcomes[outcome] = outcomes.get(outcome, 0) + 1
    for problem in ("True:", "True:bad packet", "False:no answer within timeout_ms",
                    "False:no answer within timeout_ms (and a bad packet)", "False:answers longer than expected"):
        assert outcomes.get(problem, 0) > 0, outcomes  # every way out was met


def test_the_running_cycle_uses_the_compiled_checks_and_pure_python_the_references(monkeypatch: Any) -> None:
    monkeypatch.delenv("RTLOOP_PURE_PYTHON", raising=False)  # (a suite run with it set for everything)
    device = _six_servos("dynamixel")
    assert device.goals.protocol.checks.compiled and device.state.protocol.checks.compiled
    assert device.state.take is not None  # the sync read's scanning loop in C too
    assert not PROTOCOLS["dynamixel"].checks.compiled  # the model and the set-up: the references
    monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
    assert not for_the_cycle("feetech").checks.compiled
    python = _six_servos("feetech")
    assert not python.state.protocol.checks.compiled and python.state.take is None


def _six_servos(kind: str) -> Any:
    model = "XM430-W350" if kind == "dynamixel" else "STS3215"
    return servos_answering_at_once(kind, "arm", [{"name": f"j{i}", "id": i, "model": model, "range_rad": [-1, 1]}
                                                  for i in range(1, 7)])


@pytest.mark.parametrize(("pure_python", "cycles"), [(False, 10_000), (True, 1_000)], ids=["compiled", "python"])
@pytest.mark.parametrize("kind", ["dynamixel", "feetech"])
def test_the_cycle_keeps_nothing_allocated(kind: str, pure_python: bool, cycles: int, monkeypatch: Any) -> None:
    """10,000 cycles of the running cycle (1,000 of the Python references': tracemalloc slows them ~5x)."""
    if pure_python:
        monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
    else:
        monkeypatch.delenv("RTLOOP_PURE_PYTHON", raising=False)
    device = _six_servos(kind)
    assert device.state.protocol.checks.compiled is not pure_python
    y, u = np.zeros(device.n_outputs), np.full(6, -0.1)
    for _ in range(100):
        device.write(u)
        device.read(y)
    servos = [tracemalloc.Filter(True, "*rtloop/io/servos/*")]
    tracemalloc.start()
    before = tracemalloc.take_snapshot().filter_traces(servos)
    for _ in range(cycles):
        device.write(u)
        device.read(y)
    after = tracemalloc.take_snapshot().filter_traces(servos)
    tracemalloc.stop()
    grown = [stat for stat in after.compare_to(before, "lineno") if stat.size_diff > 0]
    assert not grown, grown
    assert device.stale_reads == 0 and np.all(np.abs(y[:6] - 0.0) < 1.0)


class _AnswersOfSome:
    """A line on which only the servos of ``answering`` answer each sync read (once per request)."""

    def __init__(self, kind: str, model: str, answering: list[int]) -> None:
        from rtloop.io.servos.model import build_bus

        self.bus = build_bus(kind, answering, [model] * len(answering), 0.002) if answering else None
        self.pending = b""

    def send(self, data: Any) -> None:
        self.pending = bytes(self.bus.receive(bytes(data))) if self.bus is not None else b""

    def receive(self, buffer: memoryview, timeout_ns: int) -> int:
        answers, self.pending = self.pending, b""  # then nothing more within the timeout
        buffer[:len(answers)] = answers
        return len(answers)

    def flush_input(self) -> None:
        self.pending = b""


def test_the_stale_fault_names_the_servo_that_went_silent_not_every_one_the_last_read_missed() -> None:
    from rtloop.errors import DeviceFault
    from rtloop.io.device import build_device
    from rtloop.io.servos.line import ModelLine
    from rtloop.io.servos.model import build_bus

    servos = [{"name": name, "id": i, "model": "STS3215", "range_rad": [-1, 1]}
              for i, name in enumerate(("pan", "lift", "elbow"), start=1)]
    device = build_device("feetech", "arm", {"port": "/dev/ttyX", "servos": servos, "on_missing": "stale",
                                             "max_stale_in_a_row": 3}, "app.toml")
    device.attach(ModelLine(build_bus("feetech", [1, 2, 3], ["STS3215"] * 3, 0.002)))
    device.activate()
    y, u = np.zeros(device.n_outputs), np.zeros(3)
    device.line = _AnswersOfSome("feetech", "STS3215", [1, 2])  # servo 3 (elbow) went silent
    for _ in range(2):
        device.write(u)
        device.read(y)
    device.line = _AnswersOfSome("feetech", "STS3215", [])  # one read that none answers: the 3rd of elbow's
    device.write(u)
    with pytest.raises(DeviceFault) as fault:
        device.read(y)
    said = str(fault.value)
    assert "servo 3 (elbow) did not answer the sync read on /dev/ttyX for 3 reads in a row" in said, said
    assert "1 (pan)" not in said and "2 (lift)" not in said, said  # they missed this one read only
    assert device.stale_by_servo == [1, 1, 3]
