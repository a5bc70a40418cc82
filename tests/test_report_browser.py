"""The report in a real browser at 1366 px: no horizontal scrolling, the figures load, units on the axes.

Headless chromium renders report.html of a JIWY run and of a run-vs-simulation comparison;
the test reads the page's scroll width back from the DOM and keeps the screenshots
(``RTLOOP_SCREENSHOTS=DIR`` copies them there for a person to look at).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import rtloop
from rtloop.report import build_report

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
PAGE_WIDTH_PX = 1366
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium here (Debian: apt-get install chromium)")


def chromium(tmp_path: Path, *args: str, height_px: int = 2400) -> subprocess.CompletedProcess[str]:
    profile = tmp_path / f"chromium-profile-{len(list(tmp_path.glob('chromium-profile-*')))}"
    command = [CHROMIUM, "--headless", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-quic",
               "--hide-scrollbars", f"--user-data-dir={profile}", f"--window-size={PAGE_WIDTH_PX},{height_px}", *args]
    if os.geteuid() == 0:
        command.insert(1, "--no-sandbox")  # chromium refuses to run as root with its sandbox
    return subprocess.run(command, capture_output=True, text=True, timeout=120)


def page_width_px_and_screenshot(tmp_path: Path, html: Path, name: str) -> tuple[int, Path]:
    """document.documentElement.scrollWidth of the page at 1366 px, read from the DOM chromium dumps,
    and a screenshot of the whole page, from one browser start."""
    probe = html.with_name(f"{name}.html")
    probe.write_text(html.read_text().replace(
        "</body>", "<script>document.title = 'width=' + document.documentElement.scrollWidth + ' images=' + "
                   "Array.from(document.images).filter(i => i.complete && i.naturalWidth > 0).length;"
                   "</script></body>"))
    png = tmp_path / f"{name}.png"
    result = chromium(tmp_path, "--dump-dom", f"--screenshot={png}", probe.as_uri(), height_px=6000)  # the whole page
    match = re.search(r"<title>width=(\d+) images=(\d+)</title>", result.stdout)
    assert match, result.stdout[:500]
    assert int(match.group(2)) == html.read_text().count("<img"), "every figure loads"
    assert png.is_file(), result.stderr[-2000:]
    from matplotlib.image import imread

    pixels = imread(png)
    assert pixels.shape[1] == PAGE_WIDTH_PX and float(np.std(pixels)) > 0.05, "a page, not a blank"
    keep = os.environ.get("RTLOOP_SCREENSHOTS")
    if keep:
        Path(keep).mkdir(parents=True, exist_ok=True)
        shutil.copy(png, Path(keep) / png.name)
    return int(match.group(1)), png


def jiwy_app_file(tmp_path: Path, name: str) -> Path:
    """examples/jiwy/jiwy.toml under a name of its own, without its ROS 2 bridges (jiwy_models on the path)."""
    text = (EXAMPLES / "jiwy" / "jiwy.toml").read_text()
    text = text.split("# ROS 2 topics")[0].replace('name = "jiwy"', f'name = "{name}"')
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


@pytest.mark.slow
@pytest.mark.timeout(900)  # two runs, two reports, two browser starts: minutes on a loaded machine
def test_jiwy_run_and_its_simulation_read_at_1366_px(tmp_path: Path, rtloop_env) -> None:
    name = f"jiwy_browser_{os.getpid() % 100000}"
    app_file = jiwy_app_file(tmp_path, name)
    feed = ["--feed", f"setpoint={EXAMPLES / 'jiwy' / 'setpoints' / 'step.csv'}"]
    run_dir, sim_dir = tmp_path / "jiwy-run", tmp_path / "jiwy-sim"
    # the run and its simulation at once (nothing here looks at the run's timing); 2 s: the step at 0.5 s and
    # its settling in the signals figure
    started = [subprocess.Popen([sys.executable, "-m", "rtloop.cli", command, str(app_file), "--duration", "2",
                                 "--out", str(out), "-q", *feed], env=rtloop_env, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
               for command, out in (("run", run_dir), ("simulate", sim_dir))]
    for process in started:
        try:
            _, stderr = process.communicate(timeout=300)
        finally:
            if process.poll() is None:
                process.kill()
                process.communicate()
        assert process.returncode == 0, stderr
    run = rtloop.load(run_dir)
    assert run.signals.units["plant.AnglePan"] == "rad"

    # the comparison by `rtloop report` in a process of its own, drawn while this one draws the run's
    # report and the browser reads it (seconds of figures each)
    comparing = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "report", str(run_dir), str(sim_dir), "--out",
                                  str(tmp_path / "compare")], env=rtloop_env, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
    try:
        single = build_report([run_dir])
        assert single.html is not None
        html = single.html.read_text()
        assert "thesis criterion" in html and ("met:" in html or "not met:" in html)
        assert page_width_px_and_screenshot(tmp_path, single.html, "jiwy-run-report")[0] <= PAGE_WIDTH_PX
        _, stderr = comparing.communicate(timeout=600)
    finally:
        if comparing.poll() is None:
            comparing.kill()
            comparing.communicate()
    assert comparing.returncode == 0, stderr
    compared = tmp_path / "compare" / "report.html"
    assert compared.is_file() and (tmp_path / "compare" / "report-figures" / "compare-signals.png").is_file()
    assert page_width_px_and_screenshot(tmp_path, compared, "jiwy-run-vs-simulation-report")[0] <= PAGE_WIDTH_PX


def test_the_signal_axes_carry_units(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from rtloop.report import signals as signal_figures

    monkeypatch.syspath_prepend(str(EXAMPLES / "jiwy"))
    app_file = jiwy_app_file(tmp_path, f"jiwy_units_{os.getpid() % 100000}")
    from rtloop.app.appfile import load_app

    rtloop.simulate(load_app(app_file), 1.0, tmp_path / "sim")
    run = rtloop.load(tmp_path / "sim")
    fig = signal_figures.signals_figure("sim", run.signals, run.inputs)
    labels = [ax.get_ylabel() for ax in fig.get_axes()]
    assert labels[:2] == ["[rad]", "[rad]"]  # pan and tilt, each over its setpoint
    legend = [t.get_text() for t in fig.get_axes()[0].get_legend().get_texts()]
    assert legend == ["plant.AnglePan [rad]", "controller.SetPointPan (setpoint) [rad]"]
