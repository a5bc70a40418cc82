"""`rtloop service`: the unit it prints verifies with systemd-analyze; --install writes it once."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rtloop.cli.main import main as cli_main

REPO = Path(__file__).resolve().parent.parent
JIWY = REPO / "examples" / "jiwy" / "jiwy.toml"
SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
needs_systemd_analyze = pytest.mark.skipif(
    SYSTEMD_ANALYZE is None, reason="systemd-analyze is not installed (Debian package `systemd`)"
)

TEST_APP = """\
name = "svc_test_{pid}"

[tasks.fast]
runnable = "rt_test_runnables:Counter"
period_ns = 1_000_000
priority = 70
cpu = {cpu}

[tasks.slow]
runnable = "rt_test_runnables:Noop"
period_ns = 250_000_000
policy = "other"
"""


@pytest.fixture
def test_app(tmp_path: Path) -> Path:
    folder = tmp_path / "apps with space"
    folder.mkdir()
    path = folder / "svc.toml"
    path.write_text(TEST_APP.format(pid=os.getpid(), cpu=max(os.sched_getaffinity(0))))
    return path


def unit_text(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert cli_main(["service", *argv]) == 0
    return capsys.readouterr().out


def verify(unit: str, folder: Path, name: str) -> subprocess.CompletedProcess[str]:
    path = folder / name
    path.write_text(unit)
    assert SYSTEMD_ANALYZE is not None
    return subprocess.run([SYSTEMD_ANALYZE, "verify", "--man=no", str(path)],
                          capture_output=True, text=True, timeout=60)


def directives(unit: str) -> dict[str, list[str]]:
    found: dict[str, list[str]] = {}
    for line in unit.splitlines():
        if line and not line.startswith(("#", "[")):
            key, _, value = line.partition("=")
            found.setdefault(key, []).append(value)
    return found


@needs_systemd_analyze
def test_jiwy_unit_verifies(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    unit = unit_text([str(JIWY)], capsys)
    result = verify(unit, tmp_path, "rtloop-jiwy.service")
    assert (result.returncode, result.stderr) == (0, "")
    found = directives(unit)
    exec_start = found["ExecStart"][0].split()
    assert exec_start[-6:] == ["run", str(JIWY), "--out", "/var/lib/rtloop/jiwy/latest", "--keep", "60"]
    assert "--duration" not in exec_start
    assert Path(exec_start[0]).is_absolute()
    assert found["StateDirectory"] == ["rtloop/jiwy"]
    assert found["KillSignal"] == ["SIGINT"]
    assert found["Restart"] == ["on-failure"]
    assert found["LimitRTPRIO"] == ["99"] and found["LimitMEMLOCK"] == ["infinity"]
    assert "CPUAffinity" not in found and "User" not in found
    assert "controller → CPU 1, plant → CPU 1" in unit
    assert "Description" in found and "jiwy" in found["Description"][0]


@needs_systemd_analyze
def test_test_app_unit_with_options_verifies(test_app: Path, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "rec 100%"
    unit = unit_text([str(test_app), "--user", "rtloopsvc", "--supervisor-cpus", "0", "--keep", "30",
                      "--out", str(out)], capsys)
    name = f"rtloop-svc_test_{os.getpid()}.service"
    result = verify(unit, tmp_path, name)
    assert (result.returncode, result.stderr) == (0, "")
    found = directives(unit)
    assert found["User"] == ["rtloopsvc"]
    assert found["CPUAffinity"] == ["0"]
    assert "StateDirectory" not in found  # recordings outside /var/lib/rtloop: the user's folder
    # paths with a space are quoted, % is doubled so that systemd does not read a specifier
    assert f'"{test_app}"' in found["ExecStart"][0]
    assert '"' + str(out).replace("%", "%%") + '" --keep 30' in found["ExecStart"][0]
    assert "Not pinned: slow" in unit


@needs_systemd_analyze
def test_verify_reports_a_bad_setting(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The check above can fail: systemd-analyze exits 0 on a bad value but says so on stderr."""
    unit = unit_text([str(JIWY)], capsys).replace("LimitRTPRIO=99", "LimitRTPRIO=abc")
    result = verify(unit, tmp_path, "rtloop-jiwy.service")
    assert result.returncode == 0 and "rtloop-jiwy.service:" in result.stderr and "ignoring: abc" in result.stderr


def test_deadline_task_as_user_gets_cap_sys_nice(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    app = tmp_path / "dl.toml"
    app.write_text(f'name = "svc_dl_{os.getpid()}"\n[tasks.d]\nrunnable = "rt_test_runnables:Noop"\n'
                   'period_ns = 1_000_000\npolicy = "deadline"\n')
    as_user = directives(unit_text([str(app), "--user", "rtloopsvc"], capsys))
    assert as_user["AmbientCapabilities"] == ["CAP_SYS_NICE"]
    as_root = directives(unit_text([str(app)], capsys))
    assert "AmbientCapabilities" not in as_root and "User" not in as_root


def test_ros_domain_id_is_passed_through(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert directives(unit_text([str(JIWY)], capsys))["Environment"] == ["PYTHONUNBUFFERED=1", "ROS_DOMAIN_ID=42"]
    monkeypatch.delenv("ROS_DOMAIN_ID")
    assert directives(unit_text([str(JIWY)], capsys))["Environment"] == ["PYTHONUNBUFFERED=1"]


def test_install_writes_then_refuses_a_different_unit(test_app: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    unit_dir = tmp_path / "units"
    unit_dir.mkdir()
    path = unit_dir / f"rtloop-svc_test_{os.getpid()}.service"
    printed = unit_text([str(test_app)], capsys)

    assert cli_main(["service", str(test_app), "--install", "--unit-dir", str(unit_dir)]) == 0
    said = capsys.readouterr().out
    assert path.read_text() == printed
    assert oct(path.stat().st_mode & 0o777) == "0o644"
    assert f"systemctl link {path}" in said and f"systemctl enable --now {path.name}" in said  # not in /etc: linked

    assert cli_main(["service", str(test_app), "--install", "--unit-dir", str(unit_dir)]) == 0  # same text: fine
    assert "nothing written" in capsys.readouterr().out

    assert cli_main(["service", str(test_app), "--install", "--unit-dir", str(unit_dir), "--keep", "5"]) == 2
    assert "--force" in capsys.readouterr().err
    assert path.read_text() == printed

    assert cli_main(["service", str(test_app), "--install", "--unit-dir", str(unit_dir), "--keep", "5", "--force"]) == 0
    assert "--keep 5" in path.read_text()
    assert sorted(p.name for p in unit_dir.iterdir()) == [path.name]  # no temporary file left


def test_install_into_a_missing_folder_says_so(test_app: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["service", str(test_app), "--install", "--unit-dir", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--unit-dir" in err and "nope: no such folder" in err


def test_a_unit_outside_systemds_folders_is_linked_not_reloaded(test_app: Path, tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["service", str(test_app), "--install", "--unit-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "daemon-reload" not in out and f"systemctl link {tmp_path}/rtloop-" in out
    assert "systemd does not look in" in out


@pytest.mark.parametrize(("content", "expected"), [
    (None, "no such file"),
    ("name = \n", "not valid TOML"),
    ('name = "svc_bad"\n[tasks.a]\nrunable = "x:Y"\n', "did you mean 'runnable'"),
])
def test_bad_app_file_is_one_line_and_exit_2(tmp_path: Path, rtloop_env: dict[str, str],
                                             content: str | None, expected: str) -> None:
    app = tmp_path / "bad.toml"
    if content is not None:
        app.write_text(content)
    result = subprocess.run([sys.executable, "-m", "rtloop.cli", "service", str(app)],
                            capture_output=True, text=True, env=rtloop_env, timeout=60)
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert result.stderr.startswith("rtloop service: ") and expected in result.stderr


@pytest.mark.parametrize("option", [
    ["--keep", "0"], ["--user", "bad name"], ["--supervisor-cpus", "0;1"], ["--supervisor-cpus", "3-1"],
])
def test_bad_option_is_exit_2(option: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["service", str(JIWY), *option]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and option[0] in err


SUDO_USER_APP = """\
name = "svc_sudo_{pid}"

[tasks.t]
runnable = "{module}:Here"
period_ns = 1_000_000
policy = "other"
"""

HERE_MODULE = ("from rtloop import Runnable\n\n\nclass Here(Runnable):\n    n_inputs, n_outputs = 0, 1\n\n"
               "    def step(self, u, y):\n        y[0] = 1.0\n")


@pytest.mark.skipif(os.geteuid() != 0, reason="plays a sudo user: needs root to chown")
def test_install_refuses_code_the_services_user_would_refuse(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    import pwd

    nobody = pwd.getpwnam("nobody")
    clone = tmp_path / "clone"  # a sudo user's clone: their folder, their module
    clone.mkdir()
    module = f"svc_models_{os.getpid()}"
    (clone / f"{module}.py").write_text(HERE_MODULE)
    app_file = clone / "svc.toml"
    app_file.write_text(SUDO_USER_APP.format(pid=os.getpid(), module=module))
    for path in (clone, clone / f"{module}.py", app_file):
        os.chown(path, nobody.pw_uid, nobody.pw_gid)
    units = tmp_path / "units"
    units.mkdir()
    monkeypatch.setenv("SUDO_UID", str(nobody.pw_uid))  # sudo rtloop service ... --install
    monkeypatch.setenv("SUDO_GID", str(nobody.pw_gid))
    assert cli_main(["service", str(app_file), "--install", "--unit-dir", str(units)]) == 2
    error = capsys.readouterr().err
    assert len(error.strip().splitlines()) == 1, error
    assert f"is owned by uid {nobody.pw_uid}, not by root" in error
    assert "--user nobody" in error and "copy the app to a folder only root can write" in error
    assert list(units.iterdir()) == []  # nothing installed that would fail at every start
    assert cli_main(["service", str(app_file), "--install", "--unit-dir", str(units), "--user", "nobody"]) == 0
    assert len(list(units.iterdir())) == 1


@pytest.mark.skipif(os.geteuid() != 0, reason="plays a sudo user: needs root to chown")
def test_install_refuses_a_model_the_services_user_would_refuse(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    fmu = tmp_path / "plant.fmu"
    fmu.write_bytes(b"PK\x05\x06" + bytes(18))
    os.chown(fmu, 65534, 65534)
    app_file = tmp_path / "svc.toml"
    app_file.write_text(f'name = "svc_fmu_{os.getpid()}"\n[tasks.t]\nmodel = "fmu:plant.fmu"\nperiod_ns = 1_000_000\n')
    monkeypatch.setenv("SUDO_UID", "65534")
    monkeypatch.setenv("SUDO_GID", "65534")
    assert cli_main(["service", str(app_file), "--install", "--unit-dir", str(tmp_path)]) == 2
    error = capsys.readouterr().err
    assert f"would refuse the app's code: {fmu} is owned by uid 65534, not by root" in error, error
