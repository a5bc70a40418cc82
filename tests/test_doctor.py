"""Tests of ``rtloop doctor``: fake /proc, /sys and /etc trees with known verdicts."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from rtloop.cli.main import main as cli_main
from rtloop.linux.rt import CAP_IPC_LOCK, CAP_SYS_NICE
from rtloop.toolbox import doctor
from rtloop.toolbox.doctor import Check, format_human, run_checks, to_json, verdict

LIMITS_HEADER = "Limit                     Soft Limit           Hard Limit           Units     \n"


def _limits(rtprio: str, memlock: str) -> str:
    """A /proc/self/limits text with the two limits the doctor reads."""
    return (
        LIMITS_HEADER
        + f"{'Max locked memory':<26}{memlock:<21}{memlock:<21}bytes     \n"
        + f"{'Max realtime priority':<26}{rtprio:<21}{rtprio:<21}\n"
    )


# A Raspberry Pi 4 made ready as docs/raspberry-pi.md says, seen by a non-root user.
READY_PI: dict[str, str] = {
    "sys/kernel/realtime": "1",
    "proc/sys/kernel/version": "#1 SMP PREEMPT_RT Mon Jan 1 00:00:00 UTC 2026",
    "proc/sys/kernel/sched_rt_runtime_us": "950000",
    "proc/sys/kernel/sched_rt_period_us": "1000000",
    "proc/cmdline": "console=tty1 root=/dev/mmcblk0p2 isolcpus=3 nohz_full=3 rcu_nocbs=3",
    "sys/devices/system/cpu/present": "0-3",
    "sys/devices/system/cpu/isolated": "3",
    **{f"sys/devices/system/cpu/cpu{n}/cpufreq/scaling_governor": "performance" for n in range(4)},
    "sys/devices/system/cpu/smt/control": "notsupported",
    "sys/devices/system/cpu/smt/active": "0",
    "proc/self/status": "Name:\tpython3\nCapEff:\t0000000000000000\n",
    "proc/self/limits": _limits("98", "unlimited"),
    "etc/security/limits.d/99-realtime.conf": (
        "# rtloop: real-time limits\n@realtime - rtprio 98\n@realtime - memlock unlimited\n"
    ),
    "etc/group": "root:x:0:\nrealtime:x:1001:pi\n",
    "dev/cpu_dma_latency": "",
    "proc/cpuinfo": "processor\t: 0\nFeatures\t: fp asimd evtstrm crc32 cpuid\n",
    "proc/swaps": "Filename\t\t\t\tType\t\tSize\t\tUsed\t\tPriority\n",
    "sys/devices/system/clocksource/clocksource0/current_clocksource": "arch_sys_counter",
    "sys/devices/system/clocksource/clocksource0/available_clocksource": "arch_sys_counter",
    "proc/1/comm": "systemd",
    # the isolated CPU 3 takes no device interrupt: the SD card's and the Ethernet's are on CPU 0
    "proc/interrupts": ("           CPU0       CPU1       CPU2       CPU3\n"
                        " 33:     981235          0          0          0     GICv2 158 Level     mmc1, mmc0\n"
                        " 39:      40211          0          0          0     GICv2 189 Level     eth0\n"
                        "IPI0:      1200       1300       1100         12       Rescheduling interrupts\n"),
    "proc/irq/33/smp_affinity_list": "0-3",
    "proc/irq/33/effective_affinity_list": "0",
    "proc/irq/39/smp_affinity_list": "0-3",
    "proc/irq/39/effective_affinity_list": "0",
}


def make_tree(root: Path, changes: dict[str, str | None] | None = None) -> Path:
    """Write READY_PI under root with ``changes`` applied (None deletes a file)."""
    files: dict[str, str | None] = {**READY_PI, **(changes or {})}
    for relative, text in files.items():
        if text is None:
            continue
        path = root / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + ("\n" if text and not text.endswith("\n") else ""))
    return root


def check_named(checks: list[Check], name: str) -> Check:
    matches = [check for check in checks if check.name == name]
    assert len(matches) == 1, f"expected one check named {name}, got {checks}"
    return matches[0]


@pytest.fixture
def holds_dma_latency(monkeypatch: pytest.MonkeyPatch) -> None:
    """Pretend rtloop already holds /dev/cpu_dma_latency at 0 while running."""
    monkeypatch.setattr(doctor, "RTLOOP_HOLDS_CPU_DMA_LATENCY", True)


def test_ready_pi_is_ok_everywhere(tmp_path: Path, holds_dma_latency: None) -> None:
    checks = run_checks(make_tree(tmp_path))
    assert [c for c in checks if c.status != "ok"] == []
    assert verdict(checks) == "ok"
    assert all(check.fix == "" for check in checks)


EXPECTED = [
    # (check, changes to READY_PI, expected status, words the detail must contain)
    ("preemption", {"sys/kernel/realtime": None}, "ok", "PREEMPT_RT"),
    ("preemption", {"sys/kernel/realtime": "0"}, "ok", "PREEMPT_RT"),
    ("preemption", {"sys/kernel/realtime": None,
                    "proc/sys/kernel/version": "#1 SMP PREEMPT_DYNAMIC Debian 6.1.0"},
     "warn", "mode unknown"),
    ("preemption", {"sys/kernel/realtime": None,
                    "proc/sys/kernel/version": "#1 SMP PREEMPT_DYNAMIC Debian 6.1.0",
                    "sys/kernel/debug/sched/preempt": "none voluntary (full) lazy"},
     "warn", "PREEMPT_DYNAMIC (full)"),
    ("preemption", {"sys/kernel/realtime": None,
                    "proc/sys/kernel/version": "#1 SMP PREEMPT_DYNAMIC Debian 6.1.0",
                    "sys/kernel/debug/sched/preempt": "none (voluntary) full"},
     "fail", "PREEMPT_DYNAMIC (voluntary)"),
    ("preemption", {"sys/kernel/realtime": None,
                    "proc/sys/kernel/version": "#1 SMP PREEMPT_DYNAMIC @0",
                    "dev/kmsg": "6,120,244874,-;Dynamic Preempt: none\n"},
     "fail", "PREEMPT_DYNAMIC (none)"),
    ("preemption", {"sys/kernel/realtime": None,
                    "proc/sys/kernel/version": "#1 SMP PREEMPT_DYNAMIC @0",
                    "proc/cmdline": "quiet preempt=full"},
     "warn", "PREEMPT_DYNAMIC (full)"),
    ("preemption", {"sys/kernel/realtime": None, "proc/sys/kernel/version": "#1 SMP PREEMPT x"},
     "warn", "PREEMPT kernel"),
    ("preemption", {"sys/kernel/realtime": None, "proc/sys/kernel/version": "#1 SMP Debian"},
     "fail", "not preempted"),
    ("rt_throttling", {"proc/sys/kernel/sched_rt_runtime_us": "-1"}, "ok", "off"),
    ("rt_throttling", {}, "ok", "95%"),
    ("rt_throttling", {"proc/sys/kernel/sched_rt_runtime_us": "500000"}, "warn", "50%"),
    ("rt_throttling", {"proc/sys/kernel/sched_rt_runtime_us": "0"}, "fail", "refused"),
    ("rt_throttling", {"proc/sys/kernel/sched_rt_runtime_us": "abc"}, "warn", "could not check"),
    ("isolated_cpus", {}, "ok", "CPUs 3 isolated"),
    ("isolated_cpus", {"proc/cmdline": "isolcpus=domain,managed_irq,3"}, "warn",
     "nohz_full and rcu_nocbs missing"),
    ("isolated_cpus", {"proc/cmdline": "isolcpus=3 -- nohz_full=3 rcu_nocbs=3"}, "warn",
     "missing"),  # after "--" the words are for init, not for the kernel
    ("isolated_cpus", {"sys/devices/system/cpu/isolated": "", "proc/cmdline": "quiet"}, "warn",
     "no isolated CPUs"),
    ("cpu_governor", {"sys/devices/system/cpu/cpu2/cpufreq/scaling_governor": "ondemand"},
     "warn", "cpu2=ondemand"),
    ("cpu_governor", {f"sys/devices/system/cpu/cpu{n}/cpufreq/scaling_governor": None
                      for n in range(4)}, "warn", "no cpufreq"),
    ("cpu_governor", {**{f"sys/devices/system/cpu/cpu{n}/cpufreq/scaling_governor": None
                         for n in range(4)}, "proc/cpuinfo": "flags\t\t: fpu tsc hypervisor"},
     "ok", "VM"),
    ("smt", {"sys/devices/system/cpu/smt/control": "on", "sys/devices/system/cpu/smt/active": "1"},
     "warn", "SMT"),
    ("smt", {"sys/devices/system/cpu/smt/control": "off"}, "ok", "off"),
    ("rt_priority", {"proc/self/limits": _limits("0", "unlimited")}, "fail", "SCHED_OTHER"),
    ("rt_priority", {"proc/self/limits": _limits("unlimited", "unlimited")}, "ok", "1-99"),
    ("rt_priority", {"proc/self/limits": _limits("0", "0"),
                     "proc/self/status": f"CapEff:\t{1 << CAP_SYS_NICE:016x}\n"}, "ok",
     "CAP_SYS_NICE"),
    ("memlock", {"proc/self/limits": _limits("98", "8388608")}, "warn", "8192 KiB"),
    ("memlock", {"proc/self/limits": _limits("0", "65536"),
                 "proc/self/status": f"CapEff:\t{1 << CAP_IPC_LOCK:016x}\n"}, "ok", "CAP_IPC_LOCK"),
    ("realtime_group", {}, "ok", "@realtime (members: pi)"),
    ("realtime_group", {"etc/group": "root:x:0:\n"}, "warn", "no such group yet"),
    ("realtime_group", {"etc/group": "realtime:x:1001:\n"}, "warn", "members: none yet"),
    ("realtime_group", {"etc/security/limits.conf": "alice soft rtprio 50\n"
                        "alice hard memlock unlimited\nalice soft memlock unlimited\n",
                        "etc/security/limits.d/99-realtime.conf": None}, "ok", "alice"),
    ("realtime_group", {"etc/security/limits.d/99-realtime.conf": None}, "warn", "only root"),
    ("realtime_group", {"etc/security/limits.d/99-realtime.conf": "@audio - rtprio 95\n"},
     "warn", "@audio"),
    ("realtime_group", {"etc/security/limits.d/99-realtime.conf": "# @realtime - rtprio 98\n"
                        "@realtime - memlock unlimited\n"}, "warn", "only root"),
    ("cpu_dma_latency", {"dev/cpu_dma_latency": None}, "warn", "missing"),
    ("virtualisation", {"proc/cpuinfo": "flags\t\t: fpu tsc hypervisor"}, "warn", "VM"),
    ("virtualisation", {"sys/class/dmi/id/product_name": "Standard PC (Q35 + ICH9, 2009)",
                        "sys/class/dmi/id/sys_vendor": "QEMU"}, "warn", "VM (QEMU"),
    ("virtualisation", {"sys/hypervisor/type": "xen"}, "warn", "VM (xen"),
    ("virtualisation", {".dockerenv": ""}, "ok", "docker container"),
    ("swap", {"proc/swaps": READY_PI["proc/swaps"] + "/dev/sda2 partition 1048572 0 -2\n"},
     "warn", "/dev/sda2"),
    ("clocksource", {"sys/devices/system/clocksource/clocksource0/current_clocksource": "tsc"},
     "ok", "tsc"),
    ("clocksource", {"sys/devices/system/clocksource/clocksource0/current_clocksource": "hpet",
                     "sys/devices/system/clocksource/clocksource0/available_clocksource":
                     "tsc hpet acpi_pm"}, "warn", "hpet"),
    ("clocksource", {"sys/devices/system/clocksource/clocksource0/current_clocksource":
                     "jiffies"}, "fail", "jiffies"),
    ("irqbalance", {"proc/321/comm": "irqbalance"}, "ok", "irqbalance running"),
]


@pytest.mark.parametrize(
    ("name", "changes", "status", "words"),
    EXPECTED,
    ids=[f"{name}-{status}-{i}" for i, (name, _, status, _) in enumerate(EXPECTED)],
)
def test_check_verdicts(
    tmp_path: Path, holds_dma_latency: None, name: str, changes: dict[str, str | None],
    status: str, words: str,
) -> None:
    check = check_named(run_checks(make_tree(tmp_path, changes)), name)
    assert (check.status, words in check.detail) == (status, True), check
    assert (check.fix != "") == (status != "ok"), "a fix exactly when something is wrong"


def test_cpu_dma_latency_not_held_by_rtloop_is_a_warning(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(doctor, "RTLOOP_HOLDS_CPU_DMA_LATENCY", False)
    check = check_named(run_checks(make_tree(tmp_path)), "cpu_dma_latency")
    assert check.status == "warn"
    assert "does not hold it" in check.detail
    assert "/dev/cpu_dma_latency" in check.fix


def test_cpu_dma_latency_not_writable(
    tmp_path: Path, holds_dma_latency: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(doctor, "_writable", lambda path: False)
    check = check_named(run_checks(make_tree(tmp_path)), "cpu_dma_latency")
    assert check.status == "warn"
    assert "udev" in check.fix


def test_limits_fix_has_the_limits_d_lines(tmp_path: Path) -> None:
    tree = make_tree(tmp_path, {"proc/self/limits": _limits("0", "8388608")})
    checks = {check.name: check for check in run_checks(tree)}
    for name in ("rt_priority", "memlock"):
        assert "@realtime - rtprio 98" in checks[name].fix
        assert "@realtime - memlock unlimited" in checks[name].fix
        assert "usermod -aG realtime $USER" in checks[name].fix
        assert "/etc/security/limits.d/99-realtime.conf" in checks[name].fix


def test_preemption_fix_names_the_rt_kernels(tmp_path: Path) -> None:
    tree = make_tree(tmp_path, {"sys/kernel/realtime": None,
                                "proc/sys/kernel/version": "#1 SMP PREEMPT_DYNAMIC"})
    fix = check_named(run_checks(tree), "preemption").fix
    for words in ("6.12", "linux-image-rt-amd64", "linux-image-rt-arm64", "Raspberry Pi"):
        assert words in fix


def test_verdict_is_the_worst_status() -> None:
    def check(status: str) -> Check:
        return Check("x", status, "", "")  # type: ignore[arg-type]

    assert verdict([]) == "ok"
    assert verdict([check("ok"), check("warn")]) == "warn"
    assert verdict([check("fail"), check("warn"), check("ok")]) == "fail"


def test_json_schema(tmp_path: Path) -> None:
    tree = make_tree(tmp_path, {"proc/self/limits": _limits("0", "0")})
    document = to_json(run_checks(tree))
    assert set(document) == {"checks", "verdict"}
    assert document["verdict"] == "fail"
    checks = document["checks"]
    assert isinstance(checks, list) and checks
    for entry in checks:
        assert set(entry) == {"name", "status", "detail", "fix"}
        assert entry["status"] in ("ok", "warn", "fail")
        assert all(isinstance(entry[key], str) for key in entry)
    assert json.loads(json.dumps(document)) == document


def test_format_human_shows_symbols_and_fixes(tmp_path: Path) -> None:
    tree = make_tree(tmp_path, {"proc/self/limits": _limits("0", "unlimited"),
                                "proc/swaps": READY_PI["proc/swaps"] + "/swapfile file 1 0 -2\n"})
    text = format_human(run_checks(tree))
    lines = text.splitlines()
    assert any(line.startswith("✓ preemption") for line in lines)
    assert any(line.startswith("! swap") for line in lines)
    assert any(line.startswith("✗ rt_priority") for line in lines)
    fix_at = lines.index(next(line for line in lines if line.startswith("✗ rt_priority"))) + 1
    assert lines[fix_at].lstrip().startswith("fix: sudo groupadd")
    assert text.count("fix:") == sum(1 for c in run_checks(tree) if c.status != "ok")
    assert lines[-1].startswith("verdict: fail")


def test_main_exit_codes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    warn_tree = make_tree(tmp_path / "warn", {"proc/swaps": READY_PI["proc/swaps"] + "/s f 1 0 -2"})
    assert cli_main(["doctor", "--root", str(warn_tree)]) == 0
    assert "verdict: warn" in capsys.readouterr().out
    fail_tree = make_tree(tmp_path / "fail", {"proc/self/limits": _limits("0", "0")})
    assert cli_main(["doctor", "--root", str(fail_tree), "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["verdict"] == "fail"


def _kernel_says_rt() -> bool:
    realtime = Path("/sys/kernel/realtime")
    flag = realtime.read_text().strip() if realtime.exists() else "0"
    return flag == "1" or "PREEMPT_RT" in platform.version().split()


def test_real_machine_tells_the_truth() -> None:
    checks = run_checks()
    assert [check.name for check in checks] == [check.name for check in
                                                 run_checks(Path("/nonexistent"))]
    preemption = check_named(checks, "preemption")
    assert (preemption.status == "ok") == _kernel_says_rt(), preemption
    if not _kernel_says_rt():
        assert verdict(checks) != "ok"


def test_the_command_runs_in_a_process_of_its_own() -> None:
    result = subprocess.run([sys.executable, "-m", "rtloop.cli", "doctor", "--json"],
                            capture_output=True, text=True, timeout=60, check=False)
    document = json.loads(result.stdout)
    assert result.returncode == (1 if document["verdict"] == "fail" else 0), result.stderr
    assert {entry["name"] for entry in document["checks"]} >= {
        "preemption", "rt_throttling", "isolated_cpus", "cpu_governor", "smt", "rt_priority",
        "memlock", "realtime_group", "cpu_dma_latency", "virtualisation", "swap", "clocksource",
    }


def test_the_engine_and_the_doctor_name_the_same_preemption_model() -> None:
    """They used to have a detector each: on a PREEMPT_DYNAMIC kernel without debugfs the engine's
    probe said ``PREEMPT_DYNAMIC`` where the doctor read the boot log and said ``PREEMPT_DYNAMIC (none)``.
    Both now read :func:`rtloop.linux.machine.preemption_model`."""
    from rtloop.linux import rt
    engine = rt.probe().preemption_model
    detail = check_named(run_checks(), "preemption").detail
    assert detail.startswith(f"{engine} kernel"), (engine, detail)


def test_the_preemption_model_under_a_tree_reads_the_boot_log(tmp_path: Path) -> None:
    from rtloop.linux.machine import preemption_model
    tree = make_tree(tmp_path, {"sys/kernel/realtime": None, "proc/sys/kernel/version": "#1 SMP PREEMPT_DYNAMIC @0",
                                "dev/kmsg": "6,1,0,-;Dynamic Preempt: voluntary\n"})
    assert preemption_model(tree) == "PREEMPT_DYNAMIC (voluntary)"


# --- device interrupts on the tasks' CPUs (issue 33: the disk's completion interrupt on the task's CPU) ---
DISK_ON_CPU_3 = {
    "proc/interrupts": ("           CPU0       CPU1       CPU2       CPU3\n"
                        " 33:     981235          0          0    2500000     GICv2 158 Level     mmc0\n"
                        " 39:      40211          0          0       9000     GICv2 189 Level     eth0\n"
                        " 40:          0          0          0         12     GICv2 190 Level     ttyS0\n"),
    "proc/irq/33/effective_affinity_list": "3",
    "proc/irq/39/effective_affinity_list": "3",
    "proc/irq/40/effective_affinity_list": "3",
}


def test_device_interrupts_on_the_task_cpu_are_named_with_the_fix(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(doctor, "affinity_refused", lambda root, irq: "")
    check = check_named(run_checks(make_tree(tmp_path, DISK_ON_CPU_3)), "device_irqs")
    assert check.status == "warn"
    assert "task CPU(s) 3" in check.detail
    assert "IRQ 33 mmc0 (2.5 million so far)" in check.detail and "IRQ 39 eth0 (9000 so far)" in check.detail
    assert "ttyS0" not in check.detail  # a dozen since boot delays nothing
    assert check.fix == "sudo sh -c 'for irq in 33 39; do echo 0,1,2 > /proc/irq/$irq/smp_affinity_list; done'"


def test_an_interrupt_the_kernel_will_not_move_says_so_and_how_to_keep_it_away(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(doctor, "affinity_refused",
                        lambda root, irq: "Operation not permitted" if irq == "33" else "")
    check = check_named(run_checks(make_tree(tmp_path, DISK_ON_CPU_3)), "device_irqs")
    assert "IRQ 33 mmc0 (2.5 million so far, cannot be moved: Operation not permitted)" in check.detail
    first, second = check.fix.splitlines()
    assert "for irq in 39;" in first
    assert "isolcpus=managed_irq,domain,3" in second and "--out /dev/shm" in second


def test_the_task_cpus_can_be_named(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(doctor, "affinity_refused", lambda root, irq: "")
    tree = make_tree(tmp_path)
    assert check_named(run_checks(tree), "device_irqs").status == "ok"  # CPU 3, the isolated one
    on_0 = check_named(run_checks(tree, task_cpus=[0]), "device_irqs")
    assert on_0.status == "warn" and "IRQ 33 mmc1, mmc0" not in on_0.detail and "IRQ 33 mmc0" in on_0.detail
    assert "echo 1,2,3 >" in on_0.fix


def test_the_affinity_probe_writes_the_interrupts_own_affinity_back(tmp_path: Path, monkeypatch) -> None:
    tree = make_tree(tmp_path, DISK_ON_CPU_3)
    affinity = tree / "proc/irq/33/smp_affinity_list"
    monkeypatch.setattr(doctor.os, "geteuid", lambda: 0)
    assert doctor.affinity_refused(tree, "33") == ""
    assert affinity.read_text() == "0-3"  # what it was: nothing moved
    assert doctor.affinity_refused(tree, "77") == "No such file or directory"  # not moved, and why
    monkeypatch.setattr(doctor.os, "geteuid", lambda: 1000)
    assert doctor.affinity_refused(tree, "77") == ""  # only root may ask: nothing said


def test_doctor_refuses_a_cpu_list_it_cannot_read(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["doctor", "--cpu", "one"]) == 2
    assert "--cpu 'one' is not a CPU list" in capsys.readouterr().err


def test_the_interrupt_probe_writes_nothing_where_a_write_back_may_move_the_interrupt(tmp_path, monkeypatch):
    """On an ARM GIC a mask written back may re-target the interrupt: doctor must not change the machine there."""
    affinity = tmp_path / "proc" / "irq" / "36" / "smp_affinity_list"
    affinity.parent.mkdir(parents=True)
    affinity.write_text("0-1\n")
    os.utime(affinity, ns=(1_000_000_000, 1_000_000_000))
    monkeypatch.setattr(os, "geteuid", lambda: 0)
    monkeypatch.setattr(platform, "machine", lambda: "aarch64")
    assert doctor.affinity_refused(tmp_path, "36") == ""
    assert affinity.stat().st_mtime_ns == 1_000_000_000
    monkeypatch.setattr(platform, "machine", lambda: "x86_64")
    assert doctor.affinity_refused(tmp_path, "36") == ""
    assert affinity.stat().st_mtime_ns != 1_000_000_000 and affinity.read_text() == "0-1"
