"""``rtloop bench``: each experiment leaves its run directories, a comparison report and a table.

Behaviour only (which files, which rows, which errors); no timing thresholds: the
numbers depend on the machine and whatever else runs on it.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import pytest

from rtloop.cli.main import EXIT_BAD_INPUT
from rtloop.cli.main import main as cli_main
from rtloop.linux import rt
from rtloop.toolbox import bench as experiments

DURATION = "0.5"  # each experiment runs two or more apps: what is checked is which ran where, not their timing


def table_rows(text: str) -> list[tuple[str, str]]:
    """(run, task) of every data row of the markdown tables in ``text``."""
    rows = []
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| ") and cells[0] not in ("run",) and len(cells) == len(experiments.COLUMNS):
            rows.append((cells[0], cells[1]))
    return rows


def summary(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def assert_report(out: Path) -> None:
    assert (out / "report.html").is_file()
    assert any((out / "report-figures").glob("*.png"))
    assert (out / "table.md").is_file()
    assert json.loads((out / "bench.json").read_text())["rows"]


@pytest.fixture
def reports_asked(monkeypatch: pytest.MonkeyPatch) -> list[tuple[list[Path], Path]]:
    """The run directories each experiment hands to the report writer, which writes nothing here:
    the comparison report itself (seconds of figures) is checked once, in the affinity test."""
    from rtloop.cli import bench

    asked: list[tuple[list[Path], Path]] = []
    monkeypatch.setattr(bench, "_write_report", lambda run_dirs, out: asked.append((list(run_dirs), out)))
    return asked


def assert_table_and_record(out: Path, run_dirs: list[Path], reports_asked: list[tuple[list[Path], Path]]) -> None:
    assert reports_asked == [(run_dirs, out)]
    assert (out / "table.md").is_file()
    assert json.loads((out / "bench.json").read_text())["rows"]


@pytest.fixture
def no_rt(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make the capability probe say real time is not allowed."""
    refused = replace(rt.probe(), may_use_rt=False, rt_reason="no CAP_SYS_NICE and RLIMIT_RTPRIO is 0")
    monkeypatch.setattr(rt, "probe", lambda: refused)


# --- the experiments ---------------------------------------------------------------------------
@pytest.mark.alone
@pytest.mark.rt
def test_affinity_runs_same_and_different_cores(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["bench", "affinity", "--duration", DURATION, "--out", str(tmp_path)]) == 0
    cpu, other = experiments.choose_cpus(None)
    same, different = summary(tmp_path / "same-core"), summary(tmp_path / "different-cores")
    assert [same["tasks"][t]["cpu"] for t in ("primes1", "primes2")] == [cpu, cpu]
    assert [different["tasks"][t]["cpu"] for t in ("primes1", "primes2")] == [other, cpu]
    assert [same["tasks"][t]["priority"] for t in ("primes1", "primes2")] == [80, 79]
    assert all(task["policy"] == "fifo" and task["cycles"] > 0 for task in same["tasks"].values())
    assert_report(tmp_path)
    printed = capsys.readouterr()
    expected = [("same-core", "primes1"), ("same-core", "primes2"),
                ("different-cores", "primes1"), ("different-cores", "primes2")]
    assert table_rows(printed.out) == expected
    assert table_rows((tmp_path / "table.md").read_text()) == expected
    assert f"cpus {cpu},{cpu}" in printed.out and f"cpus {other},{cpu}" in printed.out
    assert "[1/1] affinity" in printed.err


@pytest.mark.alone
@pytest.mark.rt
@pytest.mark.skipif(shutil.which("stress-ng") is None, reason="stress-ng not installed")
def test_stress_runs_quiet_and_stressed(tmp_path: Path, reports_asked, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["bench", "stress", "--duration", DURATION, "--out", str(tmp_path)]) == 0
    for run in ("quiet", "stressed"):
        assert summary(tmp_path / run)["tasks"]["primes"]["cycles"] > 0
    assert_table_and_record(tmp_path, [tmp_path / "quiet", tmp_path / "stressed"], reports_asked)
    printed = capsys.readouterr()
    assert table_rows(printed.out) == [("quiet", "primes"), ("stressed", "primes")]
    assert "stress-ng --taskset" in printed.out


@pytest.mark.alone
@pytest.mark.rt
@pytest.mark.skipif(shutil.which("cyclictest") is None, reason="cyclictest (rt-tests) not installed")
def test_cyclictest_side_by_side(tmp_path: Path, reports_asked, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["bench", "cyclictest", "--duration", DURATION, "--out", str(tmp_path)]) == 0
    assert summary(tmp_path / "rtloop")["tasks"]["noop"]["cycles"] > 0
    assert json.loads((tmp_path / "cyclictest" / "cyclictest.json").read_text())["num_threads"] == 1
    assert (tmp_path / "cyclictest" / "cyclictest.txt").is_file()
    assert_table_and_record(tmp_path, [tmp_path / "rtloop"], reports_asked)
    assert table_rows(capsys.readouterr().out) == [("rtloop", "noop"), ("cyclictest", "cyclictest")]


def test_allow_non_rt_runs_under_sched_other(tmp_path: Path, no_rt: None, reports_asked,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["bench", "affinity", "--duration", "0.5", "--out", str(tmp_path), "--allow-non-rt"]) == 0
    tasks = summary(tmp_path / "same-core")["tasks"]
    assert {t["policy"] for t in tasks.values()} == {"other"}
    assert "NOT REAL-TIME" in capsys.readouterr().err


# --- refusals and bad input --------------------------------------------------------------------
def test_refuses_without_rt_privilege(tmp_path: Path, no_rt: None, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["bench", "affinity", "--duration", DURATION, "--out", str(tmp_path / "out")]) == EXIT_BAD_INPUT
    error = capsys.readouterr().err
    assert "real-time scheduling is not allowed" in error and "--allow-non-rt" in error
    assert not (tmp_path / "out").exists()


def test_missing_stress_ng_names_the_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    real_which = shutil.which
    monkeypatch.setattr(shutil, "which", lambda name: None if name == "stress-ng" else real_which(name))
    assert cli_main(["bench", "stress", "--duration", DURATION, "--out", str(tmp_path / "out")]) == EXIT_BAD_INPUT
    assert "apt-get install stress-ng" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["latency"], "invalid choice: 'latency'"),
        ([], "the following arguments are required: experiment"),
        (["affinity", "--duration", "-1"], "must be a positive number of seconds"),
        (["affinity", "--duration", "0"], "must be a positive number of seconds"),
        (["affinity", "--duration", "ten"], "'ten' is not a number of seconds"),
        (["stress", "--stress", "cpu,disk"], "expected a comma-separated list of cpu, vm, io, cache"),
        (["affinity", "--trim", "-1"], "--trim: must be ≥ 0"),
    ],
)
def test_bad_arguments(argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["bench", *argv])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_unknown_cpu_is_refused() -> None:
    with pytest.raises(experiments.BenchError, match="--cpu 4096"):
        experiments.choose_cpus(4096)


# --- pieces --------------------------------------------------------------------------------------
def test_cyclictest_samples_use_rtloops_statistics() -> None:
    text = "Thread 0 using cpu 1.\n" + "".join(f"       0:{k:8d}:{20_000 + k:8d}\n" for k in range(100))
    text += "       0:     100: 1500000\n"  # a wake-up later than one period
    samples = experiments.parse_cyclictest_samples(text)
    assert len(samples) == 101
    settings = experiments.Settings(1.0, Path("unused"), 1, 0, "fifo", trim=0)
    row = experiments.cyclictest_row(samples, settings)
    assert (row.run, row.cycles, row.deadline_misses, row.overruns) == ("cyclictest", 101, 1, "n/a")
    assert row.latency_p50_us == pytest.approx(20.05)
    assert row.latency_max_us == pytest.approx(1500.0)


def test_markdown_table_has_one_row_per_task() -> None:
    stats = {"cpu": 1, "policy": "fifo", "priority": 80, "cycles": 10, "deadline_misses": 0, "overruns": 2,
             "jitter_over_3pct": 3, "latency_ns": {"p50": 1500.0, "p99": 2500.0, "max": None},
             "exec_ns": {"p50": 100.0}}
    rows = experiments.rows_from_summary("quiet", {"tasks": {"a": stats, "b": stats}})
    table = experiments.markdown_table(rows)
    assert table_rows(table) == [("quiet", "a"), ("quiet", "b")]
    assert "| quiet | a | 1 | fifo/80 | 10 | 1.5 | 2.5 | n/a | 0.1 | 0 | 2 | 3 |" in table


def test_rt_neighbours_leaves_out_this_process() -> None:
    found = experiments.rt_neighbours(set(os.sched_getaffinity(0)))
    assert all(f"pid {os.getpid()} " not in entry for entry in found)


def test_the_bench_apps_are_named_per_process() -> None:
    """A live app's name is its user's alone: two benches at once (two checkouts' suites) must not collide."""
    settings = experiments.Settings(1.0, Path("unused"), 1, 0, "other", trim=0)
    names = {experiments.primes_pair_app("same_core", settings, (1, 1)).name,
             experiments.single_task_app("noop", settings, experiments.NoOp(), "noop").name}
    assert names == {f"same_core_{os.getpid()}", f"noop_{os.getpid()}"}
