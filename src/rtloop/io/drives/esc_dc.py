"""The emulated ESC's distributed clocks (DC) unit: a local clock, receive-time latches, system
time offset and delay, and SYNC0 generation, at the registers ETG.1000 and the ESC datasheets give.

    0x0900-0x090F  receive times of ports 0-3 (u32, local time), latched by a write to 0x0900
    0x0910         system time (u64): local time + offset; a write is the reference clock's time
                   for the drift control (ARMW/FRMW), its difference kept at 0x092C
    0x0918         receive time of the processing unit (u64, local), latched with the ports
    0x0920         system time offset (u64), 0x0928 system time delay (u32)
    0x0980         cyclic unit control, 0x0981 activation (bit 0 cyclic operation, bit 1 SYNC0)
    0x0990         SYNC0 start time (u64, system time; read back: the next SYNC0 pulse)
    0x09A0         SYNC0 cycle time (u32, ns)

The local clock is the emulator's CLOCK_MONOTONIC plus an offset of its own per slave (as each
real ESC starts counting at its power-on), so the master has offsets to find. The frame's way
along the line is modelled as ``HOP_NS`` per slave each way, so the receive times differ as on a
cable. The emulator has no SYNC0 pin and no drift: the drive takes its outputs when the frame
passes, and the first SYNC0 pulse and the cycle are logged for the tests and for a person.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

__all__ = ["HOP_NS", "REG_DC_ACTIVATION", "REG_DC_SYNC0_CYCLE", "REG_DC_SYNC0_START", "REG_DC_SYSTEM_TIME",
           "DcUnit"]

REG_DC_RECEIVE_TIMES, REG_DC_SYSTEM_TIME, REG_DC_RECEIVE_UNIT = 0x0900, 0x0910, 0x0918
REG_DC_OFFSET, REG_DC_DELAY, REG_DC_DIFFERENCE = 0x0920, 0x0928, 0x092C
REG_DC_CYCLIC_CONTROL, REG_DC_ACTIVATION = 0x0980, 0x0981
REG_DC_SYNC0_START, REG_DC_SYNC0_CYCLE = 0x0990, 0x09A0
DC_FIRST, DC_END = 0x0900, 0x09B0
HOP_NS = 250
"""The frame's time from one slave's port 0 to the next's (cable and forwarding), each way."""
LOCAL_START_NS = 1_000_000_007
"""Each slave's local clock is this far ahead of CLOCK_MONOTONIC per position (its own power-on)."""
U64 = (1 << 64) - 1


class DcUnit:
    """One slave's DC registers in its ESC memory; ``clock`` is the emulator's CLOCK_MONOTONIC."""

    def __init__(self, memory: bytearray, position: int, slaves: int, clock: Callable[[], int],
                 log: Callable[[str], None]) -> None:
        self.memory = memory
        self.position = position
        self.slaves = slaves
        self.clock = clock
        self.log = log
        self.local_start_ns = LOCAL_START_NS * position
        self.sync0_start_ns = 0
        self.sync0_cycle_ns = 0
        self.sync0_active = False
        self.sync0_pulsed = False

    def local_ns(self) -> int:
        return (self.clock() + self.local_start_ns) & U64

    def system_ns(self) -> int:
        offset: int = struct.unpack_from("<Q", self.memory, REG_DC_OFFSET)[0]
        return (self.local_ns() + offset) & U64

    def refresh(self) -> None:
        """The read-only registers at this moment: system time, the next SYNC0 pulse."""
        now = self.system_ns()
        struct.pack_into("<Q", self.memory, REG_DC_SYSTEM_TIME, now)
        self.tick()
        if self.sync0_active and self.sync0_cycle_ns:
            start = self.sync0_start_ns
            next_pulse = start if now < start else start + ((now - start) // self.sync0_cycle_ns + 1) * \
                self.sync0_cycle_ns
            struct.pack_into("<Q", self.memory, REG_DC_SYNC0_START, next_pulse)

    def tick(self) -> None:
        """SYNC0's first pulse, logged once the system time passed the start time."""
        if self.sync0_active and not self.sync0_pulsed and self.system_ns() >= self.sync0_start_ns:
            self.sync0_pulsed = True
            self.log(f"slave {self.position}: DC SYNC0 first pulse at system time {self.sync0_start_ns} ns "
                     f"(cycle {self.sync0_cycle_ns} ns)")

    def written(self, address: int, end: int) -> None:
        """After a write to ``[address, end)`` that reaches the DC registers."""
        if address <= REG_DC_RECEIVE_TIMES < end:
            self._latch()
        if address < REG_DC_SYSTEM_TIME + 8 and end > REG_DC_SYSTEM_TIME:
            # the reference clock's time, for the drift control: its difference kept, the register not
            received, = struct.unpack_from("<Q", self.memory, REG_DC_SYSTEM_TIME)
            delay, = struct.unpack_from("<I", self.memory, REG_DC_DELAY)
            difference = ((received + delay) - self.system_ns()) & U64
            negative = difference >= 1 << 63
            magnitude = min((U64 + 1 - difference) if negative else difference, 0x7FFFFFFF)
            struct.pack_into("<I", self.memory, REG_DC_DIFFERENCE, magnitude | (0x80000000 if negative else 0))
            struct.pack_into("<Q", self.memory, REG_DC_SYSTEM_TIME, self.system_ns())
        if address <= REG_DC_ACTIVATION < end:
            self._activation()

    def _latch(self) -> None:
        """A write to 0x0900 passing: each port's receive time (port 0 on the way out, port 1 on the
        way back from the slaves behind it), and the processing unit's (64 bits)."""
        arrival = self.local_ns() + HOP_NS * (self.position - 1)
        back = arrival + 2 * HOP_NS * (self.slaves - self.position)
        struct.pack_into("<IIII", self.memory, REG_DC_RECEIVE_TIMES, arrival & 0xFFFFFFFF,
                         back & 0xFFFFFFFF if self.position < self.slaves else 0, 0, 0)
        struct.pack_into("<Q", self.memory, REG_DC_RECEIVE_UNIT, arrival & U64)

    def _activation(self) -> None:
        activation = self.memory[REG_DC_ACTIVATION]
        active = activation & 0x03 == 0x03
        if active and not self.sync0_active:
            start, = struct.unpack_from("<Q", self.memory, REG_DC_SYNC0_START)
            cycle, = struct.unpack_from("<I", self.memory, REG_DC_SYNC0_CYCLE)
            self.sync0_start_ns, self.sync0_cycle_ns = start, cycle
            self.sync0_pulsed = False
            now = self.system_ns()
            late = " (in the past: no pulse until the start time comes round)" if start < now else ""
            offset, = struct.unpack_from("<Q", self.memory, REG_DC_OFFSET)
            monotonic = (start - offset - self.local_start_ns) & U64  # this slave's clocks are the emulator's
            self.log(f"slave {self.position}: DC SYNC0 activated: start at system time {start} ns (CLOCK_MONOTONIC "
                     f"{monotonic} ns here), cycle {cycle} ns{late}")
        elif not active and self.sync0_active:
            self.log(f"slave {self.position}: DC SYNC0 deactivated")
        self.sync0_active = active
