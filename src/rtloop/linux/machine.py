"""What this machine's kernel, limits and processes say, read from files below a *root*.

``root`` is ``/`` on a live system (:data:`LIVE_ROOT`) and a fake tree in the tests; the
engine (:func:`rtloop.linux.rt.probe`) and ``rtloop doctor`` (:mod:`rtloop.toolbox.doctor`)
both read through these functions, so they cannot disagree about the same machine.
Only the standard library is used: the doctor runs before anything else is installed.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

LIVE_ROOT = Path("/")


def is_live(root: Path) -> bool:
    return Path(root).resolve() == LIVE_ROOT


def read_text(root: Path, relative: str) -> str | None:
    """The stripped text of ``root/relative``, or None if it cannot be read."""
    try:
        return (Path(root) / relative).read_text(errors="replace").strip()
    except OSError:
        return None


def kernel_command_line(root: Path = LIVE_ROOT) -> dict[str, str]:
    """Kernel command-line parameters as ``{name: value}`` (value ``""`` for flags)."""
    params: dict[str, str] = {}
    for word in (read_text(root, "proc/cmdline") or "").split():
        if word == "--":  # what follows is for init, not for the kernel
            break
        name, _, value = word.partition("=")
        params[name] = value
    return params


def kernel_log(root: Path = LIVE_ROOT, max_records: int = 100_000) -> str:
    """The kernel log ring buffer from /dev/kmsg ("" if unreadable: not root, dmesg_restrict)."""
    try:
        fd = os.open(Path(root) / "dev/kmsg", os.O_RDONLY | os.O_NONBLOCK)
    except OSError:
        return ""
    chunks: list[bytes] = []
    try:
        for _ in range(max_records):  # /dev/kmsg returns one record per read
            try:
                chunk = os.read(fd, 8192)
            except BlockingIOError:  # no more records
                break
            except BrokenPipeError:  # records overwritten while reading: go on
                continue
            if not chunk:
                break
            chunks.append(chunk)
    finally:
        os.close(fd)
    return b"".join(chunks).decode(errors="replace")


def _dynamic_preempt_mode(root: Path) -> str | None:
    """The mode of a PREEMPT_DYNAMIC kernel: debugfs's ``(chosen)`` word; without debugfs the boot
    log's ``Dynamic Preempt: none`` (the effective mode, printed once at boot); failing that,
    ``preempt=`` on the command line (what was asked for)."""
    chosen = [w for w in (read_text(root, "sys/kernel/debug/sched/preempt") or "").split() if w.startswith("(")]
    if chosen:
        return chosen[0].strip("()")
    marker = "Dynamic Preempt: "
    for line in reversed(kernel_log(root).splitlines()):
        if marker in line:
            return line.split(marker, 1)[1].split()[0]
    return kernel_command_line(root).get("preempt") or None


def preemption_model(root: Path = LIVE_ROOT) -> str:
    """``PREEMPT_RT``, ``PREEMPT_DYNAMIC (full|lazy|voluntary|none)``, ``PREEMPT_DYNAMIC`` (mode
    unknown), ``PREEMPT`` or ``unknown``.

    The kernel's version string is ``/proc/sys/kernel/version`` (what ``uname -v`` and
    ``platform.version()`` print)."""
    if read_text(root, "sys/kernel/realtime") == "1":
        return "PREEMPT_RT"
    tokens = (read_text(root, "proc/sys/kernel/version") or "").split()
    if "PREEMPT_RT" in tokens:
        return "PREEMPT_RT"
    if "PREEMPT_DYNAMIC" in tokens:
        mode = _dynamic_preempt_mode(root)
        return f"PREEMPT_DYNAMIC ({mode})" if mode else "PREEMPT_DYNAMIC"
    return "PREEMPT" if "PREEMPT" in tokens else "unknown"


def soft_limits(root: Path = LIVE_ROOT) -> dict[str, str]:
    """This process's soft limits from /proc/self/limits: ``{"Max realtime priority": "0", ...}``."""
    limits: dict[str, str] = {}
    for line in (read_text(root, "proc/self/limits") or "").splitlines()[1:]:
        name, soft = line[:26].strip(), line[26:].split()
        if soft:
            limits[name] = soft[0]
    return limits


def effective_capabilities(root: Path = LIVE_ROOT) -> int:
    """This process's effective capability bits (``CapEff`` of /proc/self/status)."""
    for line in (read_text(root, "proc/self/status") or "").splitlines():
        if line.startswith("CapEff:"):
            return int(line.split()[1], 16)
    return 0


def running_commands(root: Path = LIVE_ROOT) -> set[str]:
    """The command names (``comm``) of every process."""
    names = set()
    for comm in (Path(root) / "proc").glob("[0-9]*/comm"):
        try:
            names.add(comm.read_text().strip())
        except OSError:  # the process ended while we looked
            continue
    return names


@dataclass(frozen=True, slots=True)
class Virtualisation:
    vm: str | None
    """Hypervisor name, or None on bare metal."""
    container: str | None
    """Container technology, or None outside a container."""
    evidence: str
    """How it was detected."""


def _detect_virt_command(kind: str) -> str | None:
    """``systemd-detect-virt --vm|--container`` output, or None if the tool is missing."""
    if shutil.which("systemd-detect-virt") is None:
        return None
    try:
        result = subprocess.run(["systemd-detect-virt", f"--{kind}"], capture_output=True,
                                text=True, timeout=5, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return result.stdout.strip() or "none"


_VM_PRODUCTS = ("KVM", "QEMU", "VMware", "VirtualBox", "Virtual Machine", "Xen", "Bochs",
                "BHYVE", "Parallels", "Standard PC", "Google Compute Engine")


def _vm_from_files(root: Path) -> tuple[str | None, str]:
    dmi = " ".join(filter(None, (read_text(root, "sys/class/dmi/id/sys_vendor"),
                                 read_text(root, "sys/class/dmi/id/product_name"))))
    flags = next((line for line in (read_text(root, "proc/cpuinfo") or "").splitlines()
                  if line.startswith("flags")), "").split()
    if "hypervisor" in flags:
        return next((p for p in _VM_PRODUCTS if p in dmi), "hypervisor"), "cpuinfo hypervisor flag"
    hypervisor_type = read_text(root, "sys/hypervisor/type")
    if hypervisor_type:
        return hypervisor_type, "/sys/hypervisor/type"
    product = next((p for p in _VM_PRODUCTS if p in dmi), None)
    return (product, f"DMI: {dmi}") if product else (None, "no hypervisor flag, no DMI hint")


def detect_virtualisation(root: Path = LIVE_ROOT) -> Virtualisation:
    """Whether this is a VM or a container: ``systemd-detect-virt`` on a live system, else files."""
    root = Path(root)
    if is_live(root):
        vm, container = _detect_virt_command("vm"), _detect_virt_command("container")
        if vm is not None and container is not None:
            return Virtualisation(None if vm == "none" else vm, None if container == "none" else container,
                                  "systemd-detect-virt")
    vm, evidence = _vm_from_files(root)
    container = next((name for name, marker in (("docker", ".dockerenv"), ("podman", "run/.containerenv"))
                      if (root / marker).exists()), None)
    return Virtualisation(vm, container, evidence)
