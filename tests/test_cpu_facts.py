"""Facts that depend on the CPU architecture, checked on the machine the tests run on.

They run everywhere; tools/aarch64/run.sh runs them inside an arm64 root under qemu-user,
which is where they matter most: syscall numbers, libatomic, C11 atomics, compiled modules.
"""

from __future__ import annotations

import ctypes
import os
import platform
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

import rtloop
from rtloop.ipc import segments as shm
from rtloop.linux import rt

MACHINE = platform.machine()
ELF_MACHINE = {"x86_64": 0x3E, "aarch64": 0xB7, "armv7l": 0x28, "riscv64": 0xF3}
needs_gcc = pytest.mark.skipif(shutil.which("gcc") is None, reason="needs gcc")


def _compile_and_run(tmp_path: Path, source: str, *flags: str) -> str:
    c_file = tmp_path / "probe.c"
    c_file.write_text(textwrap.dedent(source))
    binary = tmp_path / "probe"
    subprocess.run(["gcc", "-O2", str(c_file), "-o", str(binary), *flags], check=True)
    return subprocess.run([str(binary)], check=True, capture_output=True, text=True).stdout


def _elf_machine(path: Path) -> int:
    header = path.read_bytes()[:20]
    assert header[:4] == b"\x7fELF", f"{path} is not an ELF file"
    return int.from_bytes(header[18:20], "little")


@needs_gcc
def test_sched_setattr_number_is_the_one_of_the_c_headers(tmp_path: Path) -> None:
    """rt.py carries its own table of sched_setattr numbers; the system headers must agree."""
    printed = _compile_and_run(
        tmp_path,
        """
        #include <stdio.h>
        #include <sys/syscall.h>
        int main(void) { printf("%d\\n", SYS_sched_setattr); return 0; }
        """,
    )
    assert rt._SYS_SCHED_SETATTR[MACHINE] == int(printed)


def test_sched_setattr_number_reaches_sched_setattr() -> None:
    """SCHED_OTHER through the number rt.py uses: the kernel (or qemu) knows the call."""
    attr = rt._SchedAttr(size=ctypes.sizeof(rt._SchedAttr), sched_policy=rt.POLICIES["other"])
    result = rt._libc.syscall(rt._SYS_SCHED_SETATTR[MACHINE], 0, ctypes.byref(attr), 0)
    assert result == 0, os.strerror(ctypes.get_errno())
    assert os.sched_getscheduler(0) == os.SCHED_OTHER


def test_libatomic_fence_loads_where_the_architecture_needs_it() -> None:
    if MACHINE == "x86_64" and shm._fence_function is None:
        pytest.skip("no libatomic here; x86-64 orders stores without it")
    assert shm._fence_function is not None, shm.FENCE_KIND
    assert shm.FENCE_KIND == "atomic_thread_fence from libatomic"
    assert shm._fence_function.argtypes == (ctypes.c_int,)
    shm.fence()  # a real call through the declared signature


def test_clock_nanosleep_signature_sleeps_to_an_absolute_time() -> None:
    sleeper = rt.AbsoluteSleeper()
    deadline_ns = rt.now_ns() + 2_000_000
    sleeper.sleep_until(deadline_ns)
    assert rt.now_ns() >= deadline_ns
    assert ctypes.sizeof(rt.Timespec) == 2 * ctypes.sizeof(ctypes.c_long) == 16


@needs_gcc
@pytest.mark.skipif(MACHINE != "aarch64", reason="the instructions checked are aarch64's")
def test_c11_acquire_release_compile_to_aarch64_ordered_instructions(tmp_path: Path) -> None:
    """The C hot path's seqlock relies on C11 acquire/release; gcc must emit LDAR/STLR here."""
    if shutil.which("objdump") is None:
        pytest.skip("needs objdump (binutils)")
    source = tmp_path / "seq.c"
    source.write_text(textwrap.dedent(
        """
        #include <stdatomic.h>
        #include <stdint.h>
        uint64_t read_sequence(_Atomic uint64_t *s) { return atomic_load_explicit(s, memory_order_acquire); }
        void write_sequence(_Atomic uint64_t *s, uint64_t v) { atomic_store_explicit(s, v, memory_order_release); }
        void full_fence(void) { atomic_thread_fence(memory_order_seq_cst); }
        """
    ))
    library = tmp_path / "seq.so"
    subprocess.run(["gcc", "-O2", "-std=c11", "-fPIC", "-shared", str(source), "-o", str(library)], check=True)
    listing = subprocess.run(["objdump", "-d", str(library)], check=True, capture_output=True, text=True).stdout
    assert "ldar" in listing and "stlr" in listing and "dmb\tish" in listing


def _instructions(listing: str) -> list[tuple[str, str]]:
    """(mnemonic, operands) of each instruction in ``objdump -d --no-show-raw-insn`` output."""
    found = []
    for line in listing.splitlines():
        address, tab, instruction = line.partition(":\t")
        if tab and address.strip() and instruction:
            mnemonic, _, operands = instruction.partition("\t")
            found.append((mnemonic.strip(), operands.split("//")[0].strip()))
    return found


@pytest.mark.skipif(MACHINE != "aarch64", reason="the instructions checked are aarch64's")
def test_the_compiled_hot_path_orders_its_seqlocks_with_aarch64_acquire_release() -> None:
    """The built _hotpath itself, not a probe: acquire loads (LDAR, or LDAPR with RCpc), release
    stores (STLR), the seqlock reader's acquire fence (DMB ISHLD) and the writer's release fence
    (DMB ISH), all inline: no call to libatomic's __atomic_* functions."""
    from rtloop.ipc import hotpath

    if not hotpath.c_built():
        pytest.skip(hotpath.why_python())
    if shutil.which("objdump") is None:
        pytest.skip("needs objdump (binutils)")
    library = Path(hotpath._hotpath.__file__)
    assert _elf_machine(library) == ELF_MACHINE["aarch64"]
    listing = subprocess.run(
        ["objdump", "-d", "--no-show-raw-insn", str(library)], check=True, capture_output=True, text=True
    ).stdout
    instructions = _instructions(listing)
    mnemonics = [mnemonic for mnemonic, _ in instructions]
    assert len(instructions) > 500, "objdump listed too little: the format was not understood"
    assert mnemonics.count("ldar") + mnemonics.count("ldapr") > 0, "no acquire load"
    assert mnemonics.count("stlr") > 0, "no release store"
    assert ("dmb", "ishld") in instructions, "no acquire fence (seqlock read)"
    assert ("dmb", "ish") in instructions, "no release fence (seqlock write)"
    assert "__atomic_" not in listing, "an atomic went through libatomic: not lock-free inline"


def _compiled_modules() -> list[Path]:
    package = Path(rtloop.__file__).parent
    return sorted(package.rglob("*.so"))


def test_compiled_modules_of_the_package_are_built_for_this_machine_and_import() -> None:
    modules = _compiled_modules()
    if not modules:
        from rtloop.ipc import hotpath

        pytest.skip(f"no compiled module in this rtloop: {hotpath.why_python()}")
    package_parent = Path(rtloop.__file__).parent.parent
    for path in modules:
        assert _elf_machine(path) == ELF_MACHINE[MACHINE], f"{path} is built for another CPU"
        dotted = ".".join(path.relative_to(package_parent).with_suffix("").parts).split(".cpython")[0]
        __import__(dotted)
        assert dotted in sys.modules


def test_real_time_priority_from_the_host_kernel() -> None:
    """SCHED_FIFO in a child process: under qemu-user the host kernel schedules the guest."""
    if not rt.probe().may_use_rt:
        pytest.skip(f"needs real-time scheduling: {rt.probe().rt_reason}")
    code = (
        "import os, time\n"
        "os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))\n"
        "t = time.monotonic_ns(); time.sleep(0.001)\n"
        "print(os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, time.monotonic_ns() - t)\n"
    )
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    policy, priority, slept_ns = map(int, done.stdout.split())
    assert (policy, priority) == (os.SCHED_FIFO, 10)
    assert slept_ns >= 1_000_000
    assert time.monotonic() - started < 60


def test_machine_is_known_to_rt() -> None:
    assert MACHINE in rt._SYS_SCHED_SETATTR, f"add {MACHINE}'s sched_setattr number to rt.py"
