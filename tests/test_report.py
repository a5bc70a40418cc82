"""``rtloop report``: figures agree with summary.json, bad input is reported clearly."""

from __future__ import annotations

import io
import json
import math
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from matplotlib.patches import StepPatch

from rtloop import report
from rtloop.cli.main import main as cli_main
from rtloop.report import figures
from rtloop.stats import timing

PERIOD_NS = 1_000_000
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def write_run(
    out: Path,
    tasks: dict[str, np.ndarray],
    *,
    trim: int = 20,
    rt: bool = True,
    failure: dict | None = None,
    mode: str = "run",
) -> Path:
    """A run directory whose summary.json is computed by rtloop.stats.timing, as the supervisor does."""
    out.mkdir(parents=True, exist_ok=True)
    lines = ["task,cycle,release_ns,start_ns,end_ns"]
    entries = {}
    for name, records in tasks.items():
        lines += [f"{name},{c},{r},{s},{e}" for c, r, s, e in records.tolist()]
        stats = timing.task_timing(timing.TimingSamples.from_records(records), PERIOD_NS, trim=trim).to_json()
        entries[name] = {"priority": 80 if rt else 0, "cpu": 1, "policy": "fifo" if rt else "other", "rt": rt,
                         "rt_reason": "" if rt else "sched_setscheduler: EPERM", "memory_locked": rt,
                         **stats, "stale_reads": 0, "timing_samples_dropped": 0}
    (out / "timing.csv").write_text("\n".join(lines) + "\n")
    summary = {"app": "synthetic", "mode": mode, "started": "2026-01-01T00:00:00+00:00", "duration_s": 1.0,
               "rt_capable": rt, "stopped_by": "fault" if failure else "duration", "failure": failure,
               "machine": {"kernel": "test", "preemption": "PREEMPT_RT", "cpus": [0, 1]},
               "tasks": entries, "ports": {}}
    (out / "summary.json").write_text(json.dumps(summary))
    (out / "signals.csv").write_text("t_s,a.y[0],a.y[1]\n" + "".join(
        f"{k * PERIOD_NS / 1e9!r},{math.sin(k / 50)!r},{math.cos(k / 50)!r}\n" for k in range(300)))
    return out


def synthetic_records(cycles: int = 300, seed: int = 1, skip: int | None = 150) -> np.ndarray:
    """Latency ≈ 20 µs, with huge start-up and shut-down outliers only trimming removes."""
    rng = np.random.default_rng(seed)
    cycle = np.arange(cycles, dtype=np.int64)
    if skip is not None:
        cycle = np.delete(cycle, skip)  # one skipped release: one jitter pair fewer
    release = 10**9 + cycle * PERIOD_NS
    latency = 20_000 + rng.integers(0, 15_000, cycle.size)
    latency[:3] = 5_000_000
    latency[-3:] = 4_000_000
    latency[min(100, cycles // 2)] = 900_000  # one far outlier inside the statistics: drawn as an arrow
    start = release + latency
    end = start + 50_000 + rng.integers(0, 5_000, cycle.size)
    return np.stack([cycle, release, start, end], axis=1)


@pytest.fixture
def synthetic_run(tmp_path: Path) -> Path:
    return write_run(tmp_path / "synthetic", {"a": synthetic_records(seed=1), "b": synthetic_records(seed=2)})


@pytest.fixture(scope="module")
def synthetic_report(tmp_path_factory: pytest.TempPathFactory) -> report.Report:
    """The report of the synthetic run, drawn once (seconds of figures) for the tests that only read it."""
    run = write_run(tmp_path_factory.mktemp("report") / "synthetic",
                    {"a": synthetic_records(seed=1), "b": synthetic_records(seed=2)})
    return report.build_report([run])


def assert_histograms_match_summary(run: report.Run, hists: dict[str, report.Histogram], task: str) -> None:
    entry = run.tasks[task]
    kept = entry["cycles"] - entry["trimmed"]
    for key, field in (("latency", "latency_ns"), ("exec", "exec_ns"), ("jitter", "period_jitter_ns")):
        hist = hists[key]
        assert int(hist.counts.sum()) + hist.below + hist.above == hist.n, key
        assert hist.min_ns == pytest.approx(entry[field]["min"], abs=0.05), key
        assert hist.max_ns == pytest.approx(entry[field]["max"], abs=0.05), key
        if key != "jitter":
            assert hist.n == kept, key
    # jitter pairs: consecutive kept cycles only, so at most kept − 1
    assert hists["jitter"].n <= kept - 1


def test_histograms_equal_summary_statistics(synthetic_report: report.Report) -> None:
    built = synthetic_report
    run = built.runs[0]
    for task in ("a", "b"):
        hists = built.histograms[(run.label, task)]
        assert_histograms_match_summary(run, hists, task)
        assert hists["jitter"].n == run.tasks[task]["cycles"] - run.tasks[task]["trimmed"] - 2  # one gap
        # the far outlier is beyond the axis, counted, and still the reported maximum
        assert hists["latency"].above == 1
        assert hists["latency"].max_ns == 900_000


def test_wrong_trimming_would_be_caught(synthetic_run: Path) -> None:
    """The check above can fail: untrimmed data has other extremes and counts."""
    run = report.load_run(synthetic_run)
    untrimmed = timing.wakeup_latency_ns(run.samples["a"])
    hist = report.histogram(untrimmed)
    assert hist.max_ns != run.tasks["a"]["latency_ns"]["max"]
    assert hist.n != run.tasks["a"]["cycles"] - run.tasks["a"]["trimmed"]


def test_figure_bars_are_the_histogram_counts(synthetic_run: Path) -> None:
    run = report.load_run(synthetic_run)
    series = report.task_series(run, "a")
    fig, hists = figures.task_figure("a", series, run.label)
    axes = fig.get_axes()
    for ax, key in zip(axes, ("latency", "jitter", "exec"), strict=True):
        (drawn,) = [patch for patch in ax.patches if isinstance(patch, StepPatch)]  # one artist for all bins
        counts, edges_us, _ = drawn.get_data()
        assert counts.tolist() == pytest.approx(hists[key].counts.tolist()), key
        assert edges_us.tolist() == pytest.approx((hists[key].edges_ns / figures.US).tolist()), key
        assert ax.get_yscale() == "log"
    # the 3 % lines sit at ±30 µs on the jitter axes
    xs = {round(line.get_xdata()[0], 3) for line in axes[1].get_lines()}
    assert {-30.0, 30.0} <= xs


def test_simulated_primes_report(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    assert cli_main(["simulate", str(EXAMPLES / "primes" / "primes.toml"), "--duration", "0.5",
                     "--out", str(out), "--quiet"]) == 0
    built = report.build_report([out])  # what `rtloop report DIR` draws (the command: the tests below)
    run = built.runs[0]
    assert set(run.tasks) == {"primes1", "primes2"}
    assert built.histograms == {}  # a simulated clock: latency and jitter all 0 µs, nothing to draw
    html = (out / "report.html").read_text()
    assert "simulated: no timing" in html and "Host execution time per step" in html
    assert "<tr><td class=\"name\">latency max [µs]</td><td>–</td><td>–</td></tr>" in html  # not 0.0
    assert html.count("data:image/png;base64,") == len(built.pngs) == 1  # the signals only
    assert [p.name for p in built.pngs] == ["run-signals.png"]


def test_html_is_self_contained(synthetic_report: report.Report) -> None:
    built = synthetic_report
    assert built.html is not None
    html = built.html.read_text()
    assert html.count('src="data:image/png;base64,') == len(built.pngs) == 4
    assert 'src="http' not in html and "<link" not in html
    assert "jitter max [µs]" in html and "PREEMPT_RT" in html
    assert "FAILED" not in html and "Not real-time" not in html


def test_several_runs_side_by_side(tmp_path: Path) -> None:
    shared = write_run(tmp_path / "shared", {"a": synthetic_records(seed=3)})
    isolated = write_run(tmp_path / "isolated", {"a": synthetic_records(seed=4), "c": synthetic_records(seed=5)})
    out = tmp_path / "cmp"
    assert cli_main(["report", str(shared), str(isolated), "--out", str(out)]) == 0
    html = (out / "report.html").read_text()
    assert "Runs side by side" in html
    assert "<th>shared</th><th>isolated</th>" in html
    assert (out / "report-figures" / "compare-a.png").is_file()
    assert (out / "report-figures" / "compare-c.png").is_file()
    assert not (shared / "report.html").exists()


def test_no_html(synthetic_run: Path) -> None:
    assert cli_main(["report", str(synthetic_run), "--no-html"]) == 0
    assert not (synthetic_run / "report.html").exists()
    assert len(list((synthetic_run / "report-figures").glob("*.png"))) == 4


def test_missing_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["report", str(tmp_path / "nope")]) == 2
    assert "no such run directory" in capsys.readouterr().err


def test_missing_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "timing.csv").write_text("task,cycle,release_ns,start_ns,end_ns\n")
    assert cli_main(["report", str(tmp_path)]) == 2
    assert "no summary.json" in capsys.readouterr().err
    with pytest.raises(ValueError, match=r"no summary\.json"):
        report.load_run(tmp_path)


def test_unreadable_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "summary.json").write_text("{not json")
    assert cli_main(["report", str(tmp_path)]) == 2
    assert "unreadable" in capsys.readouterr().err


@pytest.mark.parametrize("content", ["", "task,cycle,release_ns,start_ns,end_ns\n"])
def test_empty_timing_csv(synthetic_run: Path, content: str, capsys: pytest.CaptureFixture[str]) -> None:
    (synthetic_run / "timing.csv").write_text(content)
    assert cli_main(["report", str(synthetic_run)]) == 0
    err = capsys.readouterr().err
    assert "recorded no cycle" in err
    html = (synthetic_run / "report.html").read_text()
    assert "recorded no cycle" in html
    built = report.build_report([synthetic_run])
    assert built.histograms[(built.runs[0].label, "a")]["latency"].n == 0


def test_failed_run_is_shown_prominently(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    failure = {"task": "a", "cycle": 120, "phase": "step", "reason": "ZeroDivisionError: division by zero",
               "traceback": "Traceback (most recent call last):\n  ...\nZeroDivisionError: division by zero"}
    records = synthetic_records()[:121]
    run = write_run(tmp_path / "failed", {"a": records}, failure=failure)
    assert cli_main(["report", str(run)]) == 0
    assert "FAILED in task a" in capsys.readouterr().err
    html = (run / "report.html").read_text()
    assert '<div class="banner failure"><b>This run FAILED</b>' in html
    assert "ZeroDivisionError: division by zero" in html
    assert html.index("This run FAILED") < html.index("data:image/png")


def test_non_rt_warning(tmp_path: Path) -> None:
    run = write_run(tmp_path / "nonrt", {"a": synthetic_records()}, rt=False)
    html = report.build_report([run]).html.read_text()  # type: ignore[union-attr]
    assert "Not real-time" in html and "EPERM" in html


def test_too_few_cycles_to_keep_any(tmp_path: Path) -> None:
    run = write_run(tmp_path / "short", {"a": synthetic_records(cycles=30, skip=None)})
    built = report.build_report([run])
    assert built.runs[0].tasks["a"]["trimmed"] == 30
    hists = built.histograms[(built.runs[0].label, "a")]
    assert hists["latency"].n == 0 and hists["jitter"].n == 0
    assert "no samples" not in built.html.read_text()  # type: ignore[union-attr]  # drawn into the PNG, not HTML


def test_a_report_of_several_runs_leaves_no_figure_of_an_earlier_report(tmp_path: Path) -> None:
    shared = write_run(tmp_path / "shared", {"a": synthetic_records(seed=3)})
    isolated = write_run(tmp_path / "isolated", {"a": synthetic_records(seed=4)})
    assert cli_main(["report", str(shared)]) == 0
    assert (shared / "report-figures" / "run-a-timing.png").is_file()
    built = report.build_report([shared, isolated])  # what `rtloop report DIR DIR` draws, drawn once
    assert sorted(p.name for p in (shared / "report-figures").iterdir()) == sorted(p.name for p in built.pngs)


def test_a_folder_the_report_cannot_be_written_in_is_one_line_naming_it(
        synthetic_run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (synthetic_run / "report-figures").write_text("a file where the figures would go")
    assert cli_main(["report", str(synthetic_run)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "internal error" not in err, err
    assert f"cannot write the report into {synthetic_run}/" in err and "--out DIR" in err


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a tiny tmpfs needs root")
def test_a_full_disk_is_one_line_and_leaves_no_half_report(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    disk = tmp_path / "tiny"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.strip()}")
    try:
        run = write_run(disk / "run", {"a": synthetic_records(seed=6)})
        stats = os.statvfs(disk)
        (disk / "fill").write_bytes(b"x" * (stats.f_bavail * stats.f_frsize - 40_000))  # one figure fits
        assert cli_main(["report", str(run)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "No space left on device" in err and "--out DIR" in err, err
        assert not (run / "report.html").exists()
        left = [p for p in run.rglob("*") if p.is_file() and (p.name.startswith(".") or p.stat().st_size == 0)]
        assert left == []  # no empty figure, no temporary page
    finally:
        subprocess.run(["umount", str(disk)], check=False)


def test_titles_and_units_with_dollars_are_drawn_as_written(synthetic_run: Path) -> None:
    """A student's ``[[plot]] title = "$\\badcmd$ cost"`` or a unit "$/h": matplotlib would read a
    pair of dollars as mathtext and fail to parse it; the report draws them literally."""
    (synthetic_run / "signals.json").write_text(json.dumps({"version": 1, "columns": {
        "a.y[0]": {"task": "a", "side": "y", "index": 0, "unit": "$/h"},
        "a.y[1]": {"task": "a", "side": "y", "index": 1, "unit": "$m$"}},
        "plots": [{"title": "$\\badcmd$ cost", "signals": ["a.y[0]", "a.y[1]"], "setpoint": None,
                   "inferred": False}]}))
    assert cli_main(["report", str(synthetic_run)]) == 0
    from rtloop.record.load import load
    from rtloop.report import signals as signal_figures

    fig = signal_figures.signals_figure("run $x$", load(synthetic_run).signals)
    assert fig.get_axes()[0].get_title(loc="left") == r"\$\badcmd\$ cost"  # matplotlib's plain dollar sign
    fig.savefig(io.BytesIO(), format="png")  # drawn, not parsed
