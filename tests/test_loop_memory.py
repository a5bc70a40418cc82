"""Memory locking of a task process: mlockall on fault, then everything its loop may touch locked in
full before T0 (linux/lean.py), so the loop takes no page fault; and how locked memory is measured."""

from __future__ import annotations

import csv
import ctypes
import errno
import os
from pathlib import Path

import pytest

import rtloop
from conftest import other_cpu, scaled_s
from rt_test_runnables import ThreadPageFaults
from rtloop import App
from rtloop.linux import memory, rt
from rtloop.linux.lean import Mapping, the_loop_touches

PYTHON = "/usr/bin/python3.11"


@pytest.mark.parametrize(("line", "touched"), [
    ("rw-p /dev/shm/rtloop-x-task", True),         # a shared segment: timing ring, record queue
    ("rw-p [heap]", True),
    ("rw-p [stack]", True),
    ("rw-p ", True),                               # anonymous: Python's arenas, numpy arrays
    ("rw-p /site-packages/numpy/_core/_multiarray_umath.so", True),  # a library's data
    ("r-xp /usr/lib/x86_64-linux-gnu/libpython3.11.so.1.0", True),  # the interpreter's code
    (f"r-xp {PYTHON}", True),
    ("r-xp /usr/lib/x86_64-linux-gnu/libc.so.6", True),
    ("r-xp /src/rtloop/ipc/_hotpath.cpython-311-x86_64-linux-gnu.so", True),
    ("r-xp /site-packages/numpy.libs/libopenblas64_p-r0.so", False),  # locked as far as it ran
    ("r--p /site-packages/numpy/_core/_multiarray_umath.so", False),
    ("---p /usr/lib/x86_64-linux-gnu/libc.so.6", False),           # a guard gap: a touch would crash
    ("r-xp [vdso]", False),
    ("r--p [vvar]", False),
])
def test_what_the_loop_may_touch_is_locked_in_full(line: str, touched: bool) -> None:
    permissions, _, path = line.partition(" ")
    assert the_loop_touches(Mapping(0x1000, 0x2000, permissions, path), PYTHON) is touched


def test_a_task_that_multiplies_matrices_in_its_loop_has_its_blas_code_locked_in_full() -> None:
    # lock_blas_buffer = true: its first product in the loop must not fault in BLAS code either
    openblas = Mapping(0x1000, 0x2000, "r-xp", "/site-packages/numpy.libs/libopenblas64_p-r0.so")
    assert the_loop_touches(openblas, PYTHON, blas=True)
    assert not the_loop_touches(openblas, PYTHON, blas=False)


SMAPS = """\
7f0000000000-7f0001000000 r-xp 00000000 08:01 1 /usr/lib/libopenblas.so
Size:              16384 kB
Rss:                2048 kB
Pss:                1024 kB
Locked:             1024 kB
VmFlags: rd ex mr mw me lo
7f0002000000-7f0002100000 rw-p 00000000 00:00 0
Size:               1024 kB
Rss:                 512 kB
Pss:                 512 kB
Locked:              512 kB
VmFlags: rd wr mr mw me lo ac
7f0003000000-7f0003100000 rw-p 00000000 00:00 0
Size:               1024 kB
Rss:                 300 kB
Pss:                 300 kB
Locked:                0 kB
VmFlags: rd wr mr mw me ac
"""


def test_locked_memory_is_the_resident_pages_of_locked_mappings(tmp_path: Path) -> None:
    # Not VmLck (the mappings' whole size: 17 MB here), not smaps' Locked (a proportional share:
    # 1.5 MB here, as the library's pages are shared with another process): 2 MB + 512 kB.
    (tmp_path / "42").mkdir()
    (tmp_path / "42" / "smaps").write_text(SMAPS)
    assert memory.locked_bytes(42, tmp_path) == (2048 + 512) * 1024
    assert memory.locked_bytes(43, tmp_path) is None


def test_a_kernel_without_mcl_onfault_locks_everything_instead(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []

    def mlockall(flags: int) -> int:
        calls.append(flags)
        if flags & rt.MCL_ONFAULT:
            ctypes.set_errno(errno.EINVAL)
            return -1
        return 0

    monkeypatch.setattr(rt, "_mlockall", mlockall)
    assert rt.lock_memory() is False
    assert calls == [rt.MCL_CURRENT | rt.MCL_FUTURE | rt.MCL_ONFAULT, rt.MCL_CURRENT | rt.MCL_FUTURE]


def test_a_refused_mlockall_is_not_retried_without_onfault(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []

    def mlockall(flags: int) -> int:
        calls.append(flags)
        ctypes.set_errno(errno.EPERM)
        return -1

    monkeypatch.setattr(rt, "_mlockall", mlockall)
    with pytest.raises(rtloop.errors.LibcError, match="MCL_ONFAULT"):
        rt.lock_memory()
    assert len(calls) == 1


@pytest.mark.rt
@pytest.mark.slow
def test_the_loop_takes_no_page_fault_over_5000_cycles(tmp_path: Path) -> None:
    # Before: with everything locked up front it took none but locked ~57 MB; locked on fault only,
    # the timing ring's pages faulted in one every 128 cycles (12 faults in 1.5 s at 1 kHz).
    app = App(f"faults_{os.getpid()}")
    task = app.add_task("t", ThreadPageFaults(), period_ns=1_000_000, cpu=other_cpu())
    app.record(task.y)
    summary = rtloop.run(app, scaled_s(6.0), tmp_path)
    assert summary.rt_capable
    with open(tmp_path / "signals.csv", newline="") as file:
        header, *rows = list(csv.reader(file))
    faults = [float(row[header.index("t.y[0]")]) for row in rows[1:]]  # row 0: the initial outputs
    assert len(faults) >= 5000
    # The thread's faults since prerun, read in each step: the same from the first step to the last.
    assert faults[-1] == faults[0], [(k, f) for k, f in enumerate(faults) if f != faults[0]][:10]
    # What the summary says it locked: the loop's memory, far less than the mappings' whole size (VmLck)
    locked = summary.tasks["t"].to_json()["locked_bytes"]
    assert 1 << 20 < locked < 60 << 20, locked
