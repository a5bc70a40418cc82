"""Is this Linux machine ready for real time, and how to fix what is not (the engine of ``rtloop doctor``).

Each check reads files under ``/proc``, ``/sys`` and ``/etc`` below a *root*
directory (``/`` on a live system, a fake tree in the tests) through the OS primitives of
:mod:`rtloop.linux.machine` (the same ones the engine's probe uses) and returns a
:class:`Check` with a verdict, what it saw and, when it is not ``ok``, the fix.
One check writes, as root only: ``device_irqs`` writes a device interrupt's own affinity back to
learn whether the kernel lets it be moved (:func:`affinity_refused`). Only the standard library
is used, so the doctor runs before anything else is
installed. ``rtloop doctor`` (:mod:`rtloop.cli.doctor`) adds the device interfaces and prints them.
"""

from __future__ import annotations

import os
import platform
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

from rtloop.linux.machine import (
    LIVE_ROOT,
    Virtualisation,
    detect_virtualisation,
    effective_capabilities,
    kernel_command_line,
    preemption_model,
    read_text,
    running_commands,
    soft_limits,
)
from rtloop.linux.rt import CAP_IPC_LOCK, CAP_SYS_NICE, parse_cpu_list

Status = Literal["ok", "warn", "fail"]

__all__ = ["LIVE_ROOT", "Check", "format_human", "run_checks", "to_json", "verdict"]

# Whether `rtloop run` holds /dev/cpu_dma_latency at 0 while tasks run, as cyclictest does: it
# does (runtime/supervisor.py, `cpu_dma_latency_held` in summary.json). The check's other
# branch, with the one-liner that holds it by hand, is for a build that would not.
RTLOOP_HOLDS_CPU_DMA_LATENCY = True

_SYMBOLS: dict[str, str] = {"ok": "✓", "warn": "!", "fail": "✗"}
_SEVERITY: dict[str, int] = {"ok": 0, "warn": 1, "fail": 2}

PREEMPT_RT_FIX = (
    "Boot a PREEMPT_RT kernel (CONFIG_PREEMPT_RT=y, in mainline Linux since 6.12).\n"
    "Debian 12: sudo apt install linux-image-rt-amd64   (arm64: linux-image-rt-arm64),\n"
    "reboot and check that `uname -v` shows PREEMPT_RT.\n"
    "Raspberry Pi: build the Raspberry Pi kernel with CONFIG_PREEMPT_RT=y or use a\n"
    "prebuilt RT kernel (see docs/raspberry-pi.md).\n"
    "Stop-gap on a PREEMPT_DYNAMIC kernel: add preempt=full to the kernel command line."
)

LIMITS_FIX = (
    "sudo groupadd -f realtime\n"
    "printf '@realtime - rtprio 98\\n@realtime - memlock unlimited\\n' \\\n"
    "    | sudo tee /etc/security/limits.d/99-realtime.conf\n"
    "sudo usermod -aG realtime $USER    # then log out and in again\n"
    "(systemd services ignore limits.d: use LimitRTPRIO=98 and LimitMEMLOCK=infinity.)"
)


@dataclass(frozen=True, slots=True)
class Check:
    """The verdict of one readiness check."""

    name: str
    """Short identifier of the check, e.g. ``preemption`` or ``swap``."""
    status: Status
    """``ok`` (ready), ``warn`` (works, with worse numbers) or ``fail`` (not real time)."""
    detail: str
    """What the check saw on this machine, in one or two sentences."""
    fix: str
    """What to do about it (commands, config lines); empty when the status is ``ok``."""


# --------------------------------------------------------------------------- reading


def _cmdline_cpus(value: str) -> str:
    """The CPU list of ``isolcpus=domain,managed_irq,2-3``-style values (``2-3``)."""
    parts = value.split(",")
    while parts and parts[0].isalpha() and parts[0] != "all":
        parts.pop(0)
    return ",".join(parts)


# --------------------------------------------------------------------------- kernel


def _check_preemption(root: Path) -> Check:
    model = preemption_model(root)
    if model == "PREEMPT_RT":
        return Check("preemption", "ok", "PREEMPT_RT kernel: fully preemptible", "")
    if model in ("PREEMPT", "PREEMPT_DYNAMIC (full)", "PREEMPT_DYNAMIC (lazy)"):
        detail = (f"{model} kernel: preemptible, but spinlocks and interrupt handlers still "
                  "block an RT task, so expect wake-up latencies of 100 µs to ms, not tens of µs")
        return Check("preemption", "warn", detail, PREEMPT_RT_FIX)
    if model == "PREEMPT_DYNAMIC":
        detail = ("PREEMPT_DYNAMIC kernel, mode unknown (none, voluntary or full: mount debugfs "
                  "and read /sys/kernel/debug/sched/preempt); at best full preemption")
        return Check("preemption", "warn", detail, PREEMPT_RT_FIX)
    version = read_text(root, "proc/sys/kernel/version") or "unreadable"
    detail = (f"{model} kernel (uname -v: {version}): kernel code is not preempted (voluntary "
              "or no preemption), so a system call or driver can delay an RT task for ms")
    return Check("preemption", "fail", detail, PREEMPT_RT_FIX)


def _check_rt_throttling(root: Path) -> Check:
    runtime = read_text(root, "proc/sys/kernel/sched_rt_runtime_us")
    period = int(read_text(root, "proc/sys/kernel/sched_rt_period_us") or 1_000_000)
    if runtime is None:
        return Check("rt_throttling", "warn", "/proc/sys/kernel/sched_rt_runtime_us is missing",
                     "check that this is a Linux kernel with real-time scheduling")
    runtime_us = int(runtime)
    if runtime_us == -1:
        detail = ("sched_rt_runtime_us = -1: RT throttling is off; a runaway RT loop can hang "
                  "its CPU for good, so keep a shell on another CPU")
        return Check("rt_throttling", "ok", detail, "")
    share = runtime_us / period
    detail = (f"sched_rt_runtime_us = {runtime_us} of {period}: RT tasks may use {share:.0%} "
              f"of each CPU per {period / 1e6:g} s, then are paused for the rest")
    if runtime_us == 0:
        return Check("rt_throttling", "fail", detail + " (so SCHED_FIFO is refused)",
                     "sudo sysctl kernel.sched_rt_runtime_us=950000")
    if share < 0.9:
        return Check("rt_throttling", "warn", detail,
                     "sudo sysctl kernel.sched_rt_runtime_us=950000   (the default)")
    detail += ("; a periodic loop with a lower duty cycle is never throttled (-1 would "
               "switch this safety net off)")
    return Check("rt_throttling", "ok", detail, "")


def _check_isolated_cpus(root: Path) -> Check:
    isolated = parse_cpu_list(read_text(root, "sys/devices/system/cpu/isolated") or "")
    params = kernel_command_line(root)
    present = parse_cpu_list(read_text(root, "sys/devices/system/cpu/present") or "0")
    last = max(present)
    fix = (f"add  isolcpus={last} nohz_full={last} rcu_nocbs={last}  to the kernel command line "
           "(Debian: GRUB_CMDLINE_LINUX in /etc/default/grub, then update-grub; Raspberry Pi: "
           f"/boot/firmware/cmdline.txt), reboot, and run tasks with --cpu {last}")
    if not isolated:
        detail = "no isolated CPUs: RT tasks share every CPU with the rest of the system"
        if len(present) == 1:
            return Check("isolated_cpus", "warn", detail + " (single-CPU machine)", "")
        return Check("isolated_cpus", "warn", detail, fix)
    cpus = ",".join(map(str, isolated))
    missing = [name for name in ("nohz_full", "rcu_nocbs") if name not in params]
    detail = f"CPUs {cpus} isolated (isolcpus={_cmdline_cpus(params.get('isolcpus', '?'))})"
    if missing:
        return Check("isolated_cpus", "warn",
                     detail + f"; {' and '.join(missing)} missing, so the timer tick and RCU "
                     "callbacks still run there", f"add {' '.join(f'{m}={cpus}' for m in missing)}"
                     " to the kernel command line")
    return Check("isolated_cpus", "ok", detail + f", nohz_full={params['nohz_full']}, "
                 f"rcu_nocbs={params['rcu_nocbs']}: use --cpu {isolated[-1]}", "")


def _check_smt(root: Path) -> Check:
    active = read_text(root, "sys/devices/system/cpu/smt/active")
    control = read_text(root, "sys/devices/system/cpu/smt/control")
    if active == "1":
        detail = "SMT (hyper-threading) is on: a sibling thread shares the RT task's core"
        fix = ("echo off | sudo tee /sys/devices/system/cpu/smt/control   (or boot with nosmt),"
               " or isolate both siblings of the RT core")
        return Check("smt", "warn", detail, fix)
    if control in ("notsupported", "notimplemented") or active is None:
        return Check("smt", "ok", "no SMT on this CPU", "")
    return Check("smt", "ok", f"SMT is off (control: {control})", "")


def _check_clocksource(root: Path) -> Check:
    base = "sys/devices/system/clocksource/clocksource0/"
    current = read_text(root, base + "current_clocksource")
    available = (read_text(root, base + "available_clocksource") or "").split()
    if current in ("tsc", "arch_sys_counter"):
        return Check("clocksource", "ok", f"{current}: read in user space, in nanoseconds", "")
    if current in ("kvm-clock", "hyperv_clocksource_tsc_page", "xen"):
        return Check("clocksource", "ok", f"{current}: a paravirtual clock (VM), cheap to read", "")
    fix = ("boot with clocksource=tsc" if "tsc" in available
           else "check the firmware/kernel for a better clocksource")
    if current == "jiffies":
        return Check("clocksource", "fail", "jiffies: a tick-resolution clock", fix)
    detail = (f"{current or 'unknown'}: every clock read is a slow system call or I/O access "
              f"(available: {' '.join(available) or 'unknown'})")
    return Check("clocksource", "warn", detail, fix)


# --------------------------------------------------------------------------- CPU power


def _check_cpu_governor(root: Path, vm: str | None) -> Check:
    files = sorted((root / "sys/devices/system/cpu").glob("cpu[0-9]*/cpufreq/scaling_governor"))
    governors = {path.parent.parent.name: path.read_text().strip() for path in files}
    if not governors:
        if vm:
            return Check("cpu_governor", "ok", "no cpufreq in this VM: the host's governor sets "
                         "the clock speed (set it to performance there)", "")
        return Check("cpu_governor", "warn", "no cpufreq: the frequency is up to the firmware",
                     "load the cpufreq driver for this CPU, or check the BIOS power settings")
    slow = {cpu: gov for cpu, gov in governors.items() if gov != "performance"}
    if not slow:
        return Check("cpu_governor", "ok", f"performance on all {len(governors)} CPUs", "")
    listed = ", ".join(f"{cpu}={gov}" for cpu, gov in slow.items())
    return Check("cpu_governor", "warn",
                 f"{listed}: the clock speeds up only after load arrives, so cycles vary",
                 "echo performance | sudo tee /sys/devices/system/cpu/cpu*/cpufreq/"
                 "scaling_governor   (or: sudo cpupower frequency-set -g performance)")


def _writable(path: Path) -> bool:
    """Whether this process may open ``path`` for writing (a seam for the tests)."""
    return os.access(path, os.W_OK)


def _check_cpu_dma_latency(root: Path) -> Check:
    device = root / "dev/cpu_dma_latency"
    why = ("a process that keeps it open with the value 0 stops CPUs from entering deep "
           "idle states, whose wake-up costs up to hundreds of µs (cyclictest does this)")
    if not device.exists():
        return Check("cpu_dma_latency", "warn", f"/dev/cpu_dma_latency is missing; {why}",
                     "use a kernel with CONFIG_PM (PM QoS), or boot with idle=poll")
    if not _writable(device):
        return Check("cpu_dma_latency", "warn", f"present but not writable by this user; {why}",
                     'echo \'KERNEL=="cpu_dma_latency", GROUP="realtime", MODE="0660"\' | sudo tee '
                     "/etc/udev/rules.d/99-cpu-dma-latency.rules && sudo udevadm trigger")
    if RTLOOP_HOLDS_CPU_DMA_LATENCY:
        return Check("cpu_dma_latency", "ok", f"writable, and rtloop holds it at 0; {why}", "")
    return Check("cpu_dma_latency", "warn",
                 f"writable, but rtloop does not hold it at 0 while running yet; {why}",
                 "while the run lasts, hold it in another shell (as a user that may write it):\n"
                 "python3 -c \"import os,signal; fd=os.open('/dev/cpu_dma_latency', os.O_WRONLY);"
                 " os.write(fd, (0).to_bytes(4, 'little')); signal.pause()\"")


# --------------------------------------------------------------------------- limits


def _check_rt_priority(root: Path) -> Check:
    if effective_capabilities(root) & (1 << CAP_SYS_NICE):
        return Check("rt_priority", "ok", "this process has CAP_SYS_NICE (root): priorities "
                     "1-99 allowed", "")
    soft = soft_limits(root).get("Max realtime priority", "0")
    if soft == "unlimited" or int(soft) > 0:
        limit = "99" if soft == "unlimited" else soft
        return Check("rt_priority", "ok", f"RLIMIT_RTPRIO = {soft}: priorities 1-{limit} allowed",
                     "")
    return Check("rt_priority", "fail", "RLIMIT_RTPRIO = 0 and no CAP_SYS_NICE: tasks fall back "
                 "to SCHED_OTHER (not real time)", LIMITS_FIX)


def _check_memlock(root: Path) -> Check:
    if effective_capabilities(root) & (1 << CAP_IPC_LOCK):
        return Check("memlock", "ok", "this process has CAP_IPC_LOCK (root): mlockall works", "")
    soft = soft_limits(root).get("Max locked memory", "0")
    if soft == "unlimited":
        return Check("memlock", "ok", "RLIMIT_MEMLOCK = unlimited: mlockall works", "")
    detail = (f"RLIMIT_MEMLOCK = {int(soft) // 1024} KiB: mlockall must lock the whole address "
              "space, far more for Python with numpy, so it fails and the loop may page-fault")
    return Check("memlock", "warn", detail, LIMITS_FIX)


def _limits_rules(root: Path) -> list[tuple[str, str, str]]:
    """``(domain, item, value)`` of pam_limits rules that set the soft limit."""
    files = [root / "etc/security/limits.conf",
             *sorted((root / "etc/security/limits.d").glob("*.conf"))]
    rules = []
    for path in files:
        try:
            lines = path.read_text().splitlines()
        except OSError:
            continue
        for line in lines:
            fields = line.split("#", 1)[0].split()
            if len(fields) == 4 and fields[1] in ("-", "soft"):
                rules.append((fields[0], fields[2], fields[3]))
    return rules


def _group_members(root: Path, group: str) -> list[str] | None:
    """Members of ``group`` from /etc/group, or None if there is no such group."""
    for line in (read_text(root, "etc/group") or "").splitlines():
        fields = line.split(":")
        if len(fields) == 4 and fields[0] == group:
            return [member for member in fields[3].split(",") if member]
    return None


def _is_empty_group(root: Path, domain: str) -> bool:
    """A ``@group`` domain with no members listed in /etc/group (or no such group)."""
    return domain.startswith(("@", "%")) and not _group_members(root, domain[1:])


def _describe_domain(root: Path, domain: str) -> str:
    if not domain.startswith(("@", "%")):
        return domain
    members = _group_members(root, domain[1:])
    if members is None:
        return f"{domain} (no such group yet)"
    return f"{domain} (members: {', '.join(members) or 'none yet'})"


def _check_realtime_group(root: Path) -> Check:
    rules = _limits_rules(root)
    unlimited = ("unlimited", "infinity", "-1")
    rtprio = {d for d, item, v in rules
              if item == "rtprio" and (v in unlimited or (v.isdigit() and int(v) > 0))}
    memlock = {d for d, item, v in rules if item == "memlock" and v in unlimited}
    ready = sorted((rtprio & memlock) - {"root"})
    if ready:
        names = "; ".join(_describe_domain(root, d) for d in ready)
        detail = f"limits.d lets {names} use RT priorities and lock memory"
        if all(_is_empty_group(root, domain) for domain in ready):
            return Check("realtime_group", "warn", detail + ", but nobody is in that group",
                         "sudo groupadd -f realtime && sudo usermod -aG realtime $USER   "
                         "(then log out and in again)")
        return Check("realtime_group", "ok", detail + " (from the next login)", "")
    if rtprio - {"root"}:
        names = ", ".join(sorted(rtprio - {"root"}))
        return Check("realtime_group", "warn", f"{names} may use RT priorities but not lock "
                     "unlimited memory", LIMITS_FIX)
    return Check("realtime_group", "warn", "no /etc/security/limits rule grants rtprio to "
                 "non-root users: only root can run RT tasks", LIMITS_FIX)


# --------------------------------------------------------------------------- environment


def _check_virtualisation(virt: Virtualisation) -> Check:
    container = f"; inside a {virt.container} container" if virt.container else ""
    if virt.vm:
        detail = (f"VM ({virt.vm}, from {virt.evidence}){container}: the hypervisor may stall "
                  "a core for ms, so latency numbers here say little about real hardware")
        return Check("virtualisation", "warn", detail,
                     "measure on bare metal; if you must use a VM, pin its vCPUs to isolated "
                     "host CPUs and run the host on a PREEMPT_RT kernel")
    if virt.container:
        return Check("virtualisation", "ok", f"bare metal, inside a {virt.container} container: "
                     "it needs --cap-add SYS_NICE --ulimit rtprio=98 --ulimit memlock=-1", "")
    return Check("virtualisation", "ok", f"bare metal ({virt.evidence})", "")


def _check_swap(root: Path) -> Check:
    text = read_text(root, "proc/swaps")
    devices = [line.split()[0] for line in (text or "").splitlines()[1:] if line.strip()]
    if not devices:
        return Check("swap", "ok", "no swap in use", "")
    detail = (f"swap on {', '.join(devices)}: mlockall keeps RT tasks in RAM, but the "
              "supervisor and bridges can still be paged out, and swapping adds I/O load")
    return Check("swap", "warn", detail, "sudo swapoff -a   (and remove the swap line from "
                 "/etc/fstab to keep it off)")


def _check_irqbalance(root: Path) -> Check:
    if "irqbalance" not in running_commands(root):
        return Check("irqbalance", "ok", "irqbalance not running: interrupts stay where the "
                     "kernel put them", "")
    return Check("irqbalance", "ok", "irqbalance running: it moves interrupts around; if an "
                 "isolated CPU still gets interrupts (see /proc/interrupts), set "
                 "IRQBALANCE_BANNED_CPULIST in /etc/default/irqbalance", "")


def default_task_cpus(root: Path) -> list[int]:
    """The CPUs tasks are meant for when none are named: the isolated ones, else the last (what
    ``isolated_cpus``' fix suggests for ``--cpu``)."""
    isolated = parse_cpu_list(read_text(root, "sys/devices/system/cpu/isolated") or "")
    return list(isolated) or [max(parse_cpu_list(read_text(root, "sys/devices/system/cpu/present") or "0"))]


def affinity_refused(root: Path, irq: str) -> str:
    """Why the kernel will not move ``irq`` ('' if it will, or if this user may not ask): the interrupt's
    own affinity written back, which moves nothing where it is allowed (x86 keeps an interrupt on its
    CPU while that CPU stays in the mask), EPERM where its driver's affinity is managed by the kernel."""
    path = Path(root) / "proc" / "irq" / irq / "smp_affinity_list"
    if os.geteuid() != 0 or platform.machine() not in WRITE_BACK_MOVES_NOTHING_ON:
        return ""  # elsewhere (an ARM GIC) a mask written back may move the interrupt: doctor changes nothing
    try:
        current = path.read_text().strip()
        with open(path, "w") as file:
            file.write(current)
    except OSError as error:
        return f"{os.strerror(error.errno) if error.errno else error}"
    return ""


WRITE_BACK_MOVES_NOTHING_ON = frozenset({"x86_64", "i686", "i386"})
"""Machines whose interrupt controllers keep an interrupt on its CPU while that CPU stays in the mask written."""

IRQS_WORTH_NAMING = 100
"""Interrupts a device has raised on a task CPU since boot before the check names it (a serial console's
dozen at boot delays nothing)."""


def _how_many(count: int) -> str:
    return f"{count / 1e6:.1f} million" if count >= 1_000_000 else str(count)


def _check_device_interrupts(root: Path, task_cpus: Sequence[int] | None) -> Check:
    cpus = sorted(set(task_cpus)) if task_cpus else default_task_cpus(root)
    text = read_text(root, "proc/interrupts")
    if not text:
        return Check("device_irqs", "ok", "/proc/interrupts not readable: device interrupts not checked", "")
    header, *rows = text.splitlines()
    column_cpus = [int(name[3:]) for name in header.split() if name.startswith("CPU")]
    named = ", ".join(map(str, cpus))
    found: list[tuple[int, str, str, str]] = []  # count on the task CPUs, irq, name, why it cannot move
    for row in rows:
        label, _, rest = row.partition(":")
        irq, fields = label.strip(), rest.split()
        if not irq.isdigit() or len(fields) <= len(column_cpus):
            continue  # LOC, RES, ...: every CPU has its own
        counts = dict(zip(column_cpus, fields, strict=False))
        affinity = (read_text(root, f"proc/irq/{irq}/effective_affinity_list")
                    or read_text(root, f"proc/irq/{irq}/smp_affinity_list") or "")
        on_tasks = set(parse_cpu_list(affinity)) & set(cpus)
        fired = sum(int(counts.get(cpu, "0")) for cpu in on_tasks if counts.get(cpu, "0").isdigit())
        if on_tasks and fired >= IRQS_WORTH_NAMING:
            found.append((fired, irq, fields[-1], affinity_refused(root, irq)))
    if not found:
        return Check("device_irqs", "ok", f"no device interrupt is handled on the task CPU(s) {named}", "")
    found.sort(reverse=True)
    said = "; ".join(f"IRQ {irq} {name} ({_how_many(fired)} so far" + (f", cannot be moved: {why}" if why else "")
                     + ")" for fired, irq, name, why in found)
    others = sorted(set(parse_cpu_list(read_text(root, "sys/devices/system/cpu/present") or "0")) - set(cpus))
    movable = [irq for _, irq, _, why in found if not why]
    fixes = []
    if movable and others:
        fixes.append(f"sudo sh -c 'for irq in {' '.join(movable)}; do echo {','.join(map(str, others))} "
                     "> /proc/irq/$irq/smp_affinity_list; done'")
    if any(why for *_, why in found):
        fixes.append(f"an interrupt the kernel will not move: boot with isolcpus=managed_irq,domain,{named}, or run "
                     "the tasks on a CPU it does not use (--cpu); a disk's: record to another disk or to RAM "
                     "(--out /dev/shm/...)")
    return Check("device_irqs", "warn", f"device interrupts on the task CPU(s) {named} delay a wake-up there "
                 f"whatever its priority: {said}", "\n".join(fixes))


# --------------------------------------------------------------------------- driver


def _guarded(name: str, check: Callable[[], Check]) -> Check:
    """Run one check; an unexpected file format becomes a warning instead of a crash."""
    try:
        return check()
    except (OSError, ValueError, IndexError) as error:
        return Check(name, "warn", f"could not check: {type(error).__name__}: {error}",
                     "please report this with the file named above")


def run_checks(root: Path = LIVE_ROOT, more: Sequence[tuple[str, Callable[[], Check]]] = (),
               task_cpus: Sequence[int] | None = None) -> list[Check]:
    """Run every readiness check against the system whose /proc, /sys and /etc are under root,
    then ``more`` (name, check) pairs, each guarded alike. ``task_cpus``: the CPUs the tasks will be
    pinned to (default: :func:`default_task_cpus`)."""
    root = Path(root)
    virt = detect_virtualisation(root)
    checks: list[tuple[str, Callable[[], Check]]] = [
        ("preemption", lambda: _check_preemption(root)),
        ("rt_throttling", lambda: _check_rt_throttling(root)),
        ("isolated_cpus", lambda: _check_isolated_cpus(root)),
        ("cpu_governor", lambda: _check_cpu_governor(root, virt.vm)),
        ("smt", lambda: _check_smt(root)),
        ("rt_priority", lambda: _check_rt_priority(root)),
        ("memlock", lambda: _check_memlock(root)),
        ("realtime_group", lambda: _check_realtime_group(root)),
        ("cpu_dma_latency", lambda: _check_cpu_dma_latency(root)),
        ("virtualisation", lambda: _check_virtualisation(virt)),
        ("swap", lambda: _check_swap(root)),
        ("clocksource", lambda: _check_clocksource(root)),
        ("irqbalance", lambda: _check_irqbalance(root)),
        ("device_irqs", lambda: _check_device_interrupts(root, task_cpus)),
        *more,
    ]
    return [_guarded(name, check) for name, check in checks]


def verdict(checks: Iterable[Check]) -> Status:
    """The worst status among the checks (``ok`` when there are none)."""
    worst: Status = "ok"
    for check in checks:
        if _SEVERITY[check.status] > _SEVERITY[worst]:
            worst = check.status
    return worst


_VERDICT_TEXT = {
    "ok": "ready for real time",
    "warn": "runs, but with worse timing than this machine could give (see the ! lines)",
    "fail": "not ready for real time (see the ✗ lines)",
}


def _fix_lines(fix: str, indent: str) -> list[str]:
    """``fix: first line`` and the following lines aligned under it."""
    return [f"{indent}{'fix: ' if i == 0 else '     '}{line}"
            for i, line in enumerate(fix.splitlines())]


def format_human(checks: list[Check]) -> str:
    """Aligned lines ``✓ name  detail`` with each non-ok check's fix indented below."""
    width = max((len(check.name) for check in checks), default=0)
    lines = ["rtloop doctor: is this machine ready for real time?", ""]
    for check in checks:
        lines.append(f"{_SYMBOLS[check.status]} {check.name:<{width}}  {check.detail}")
        if check.status != "ok" and check.fix:
            lines.extend(_fix_lines(check.fix, indent=" " * (width + 4)))
    worst = verdict(checks)
    lines += ["", f"verdict: {worst}: {_VERDICT_TEXT[worst]}"]
    return "\n".join(lines)


def to_json(checks: list[Check]) -> dict[str, object]:
    """``{"checks": [{"name", "status", "detail", "fix"}, ...], "verdict": worst status}``."""
    return {"checks": [asdict(check) for check in checks], "verdict": verdict(checks)}
