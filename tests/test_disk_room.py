"""F-duration-disk: a run with --duration (and no --keep) keeps everything, so it is refused at
start when its recording cannot fit on the disk: one line naming the estimate, the free bytes
and --keep S, exit 2, nothing written. With --keep (and without --duration) nothing is checked."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtloop.app.appfile import load_app
from rtloop.cli.main import main
from rtloop.record import disk_room

DCMOTOR = Path(__file__).resolve().parents[1] / "examples" / "dcmotor" / "dcmotor.toml"


def test_the_estimate_errs_high(tmp_path: Path) -> None:
    """What a simulation of the DC motor writes per second is below the estimate (a real run's
    stamps are longer: 0.31 MB/s measured against 0.49 MB/s estimated)."""
    assert main(["simulate", str(DCMOTOR), "--duration", "2", "--out", str(tmp_path / "sim"), "--quiet"]) == 0
    written = sum(p.stat().st_size for p in (tmp_path / "sim").iterdir())
    estimate = disk_room.recording_bytes_per_s(load_app(DCMOTOR)) * 2
    assert written < estimate < 3 * written


def test_a_recording_that_cannot_fit_is_refused_in_one_line(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "long"
    # 1e8 s of the DC motor: about 49 TB, more than any disk here has free
    code = main(["run", str(DCMOTOR), "--duration", "1e8", "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert "--duration 100000000 s would record about 49200.0 GB (492.0 kB/s" in err, err
    assert f"and {out} has " in err and " free: keep the last S seconds only with --keep S (up to --keep " in err
    assert not out.exists()  # nothing written


def test_free_space_decides(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                            capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(disk_room, "free_bytes", lambda out: 1_000_000)  # a disk with 1 MB free
    args = ["simulate", str(DCMOTOR), "--duration", "3", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 2  # ≈ 1.5 MB
    assert f"would record about 1.5 MB (492.0 kB/s, an estimate that errs high) and {tmp_path / 'a'} has 1.0 MB " \
           "free: keep the last S seconds only with --keep S (up to --keep 1 fits)" in capsys.readouterr().err
    assert main([*args, "--keep", "1", "--out", str(tmp_path / "b")]) == 0  # the flight recorder bounds it
    assert main(["simulate", str(DCMOTOR), "--duration", "1", "--quiet", "--out", str(tmp_path / "c")]) == 0


def test_only_a_run_that_keeps_everything_is_checked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    checked: list[float] = []
    monkeypatch.setattr("rtloop.runtime.session.check_room", lambda app, out, duration_s: checked.append(duration_s))
    assert main(["simulate", str(DCMOTOR), "--duration", "0.1", "--quiet", "--out", str(tmp_path / "a")]) == 0
    assert checked == [0.1]
    assert main(["simulate", str(DCMOTOR), "--duration", "0.1", "--keep", "5", "--quiet",
                 "--out", str(tmp_path / "b")]) == 0
    assert checked == [0.1]  # --keep: bounded by the flight recorder, not checked


def test_a_replay_and_a_sweep_check_what_they_will_record(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """A replay records the span it replays (a --keep run's window, not the whole run); a sweep
    its points together: each is refused in one line with its own way out (neither has --keep)."""
    assert main(["simulate", str(DCMOTOR), "--duration", "2", "--out", str(tmp_path / "sim"), "--quiet"]) == 0
    monkeypatch.setattr(disk_room, "free_bytes", lambda out: 500_000)  # a disk with 0.5 MB free
    assert main(["replay", str(tmp_path / "sim"), "--out", str(tmp_path / "replay")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err == (f"rtloop replay: the replay of 2 s would record about 984.0 kB (492.0 kB/s, an estimate that errs "
                   f"high) and {tmp_path / 'replay'} has 500.0 kB free: replay into an --out with more room"), err
    assert not (tmp_path / "replay").exists()
    assert main(["sweep", str(DCMOTOR), "--param", "pi.kp=0.02,0.04", "--duration", "1", "--processes", "1",
                 "--out", str(tmp_path / "sweep")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"rtloop sweep: 2 simulations of 1 s would record about 984.0 kB (492.0 kB/s, an estimate that "
                   f"errs high) and {tmp_path / 'sweep'} has 500.0 kB free: sweep fewer points or give a shorter "
                   "--duration"), err
    assert not (tmp_path / "sweep").exists()
