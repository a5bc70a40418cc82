"""A user who runs rtloop through sudo (tools/as-root): their own files run, what rtloop writes
stays theirs. Runs as root, playing the sudo user with SUDO_UID/SUDO_GID."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

import rtloop
from rt_test_runnables import Counter
from rtloop.app.modules import ModuleRefused, check_folders, check_owner
from rtloop.record.recorder import give_to_invoking_user
from rtloop.runtime.session import prepare_out_dir
from rtloop.sudo import invoking_user

SUDO_USER_ID = 4242  # no such user needed: ownership is a number
OTHER_USER_ID = 4343

pytestmark = pytest.mark.skipif(os.geteuid() != 0, reason="plays a sudo user: needs root to chown")


@pytest.fixture
def under_sudo(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SUDO_UID", str(SUDO_USER_ID))
    monkeypatch.setenv("SUDO_GID", str(SUDO_USER_ID))


def owned_by(path: Path, uid: int) -> Path:
    path.write_text("x = 1\n")
    os.chown(path, uid, uid)
    return path


def test_the_sudo_users_own_module_runs_another_users_does_not(tmp_path: Path, under_sudo: None) -> None:
    check_owner(owned_by(tmp_path / "mine.py", SUDO_USER_ID))
    with pytest.raises(ModuleRefused, match=f"owned by uid {OTHER_USER_ID}"):
        check_owner(owned_by(tmp_path / "planted.py", OTHER_USER_ID))


def test_code_from_the_sudo_users_folder_runs_only_under_their_sudo(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    folder = tmp_path / "clone"
    folder.mkdir()
    os.chown(folder, SUDO_USER_ID, SUDO_USER_ID)
    monkeypatch.setenv("SUDO_UID", str(SUDO_USER_ID))
    monkeypatch.setenv("SUDO_GID", str(SUDO_USER_ID))
    check_folders(folder)
    monkeypatch.delenv("SUDO_UID")
    with pytest.raises(ModuleRefused, match=f"{folder} is owned by uid {SUDO_USER_ID}"):
        check_folders(folder)


def test_without_sudo_root_runs_only_roots_modules(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("SUDO_UID", raising=False)
    with pytest.raises(ModuleRefused):
        check_owner(owned_by(tmp_path / "mine.py", SUDO_USER_ID))


def test_new_folders_and_the_last_summary_belong_to_the_sudo_user(tmp_path: Path, under_sudo: None) -> None:
    out = tmp_path / "runs" / "day1" / "first"
    prepare_out_dir(out)
    assert [(tmp_path / p).stat().st_uid for p in ("runs", "runs/day1", "runs/day1/first")] == [SUDO_USER_ID] * 3
    assert tmp_path.stat().st_uid == 0  # what existed before is not touched

    app = rtloop.App(f"sudo_user_{os.getpid()}")
    app.add_task("count", Counter(), period_ns=1_000_000, policy="other")
    run = tmp_path / "runs" / "sim"
    rtloop.simulate(app, 0.05, run)
    not_theirs = [p.name for p in (run, *run.iterdir()) if p.stat().st_uid != SUDO_USER_ID]
    assert not_theirs == []


def test_a_sweeps_folders_and_table_belong_to_the_sudo_user(tmp_path: Path, under_sudo: None) -> None:
    from rtloop.toolbox.sweep import sweep

    # root's copy of the example: in a clone a real sudo user owns, the example is theirs, not uid 4242's
    shutil.copytree(Path(__file__).parents[1] / "examples" / "dcmotor", tmp_path / "dcmotor",
                    ignore=shutil.ignore_patterns("__pycache__"))
    app_file = tmp_path / "dcmotor" / "dcmotor.toml"
    result = sweep(app_file, {"pi.kp": [0.05, 0.1]}, duration_s=0.1, out=tmp_path / "runs" / "sweep", processes=1)
    assert not [row["error"] for row in result.rows if row["error"]]
    out = tmp_path / "runs" / "sweep"
    made = [tmp_path / "runs", out, *out.iterdir(), *(out / "0").iterdir()]
    assert [p.relative_to(tmp_path) for p in made if p.stat().st_uid != SUDO_USER_ID] == []
    assert tmp_path.stat().st_uid == 0  # what existed before is not touched


@pytest.mark.parametrize(("uid", "gid"), [("abc", "4242"), ("4242", ""), ("²", "4242"), ("-1", "4242"), (" 42", "42")])
def test_a_garbled_sudo_environment_is_believed_in_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                           uid: str, gid: str) -> None:
    monkeypatch.setenv("SUDO_UID", uid)
    monkeypatch.setenv("SUDO_GID", gid)
    assert invoking_user() is None
    with pytest.raises(ModuleRefused):  # only root's own modules run
        check_owner(owned_by(tmp_path / "mine.py", SUDO_USER_ID))
    out = tmp_path / "run"
    out.mkdir()
    give_to_invoking_user(out)  # handed to nobody, and no error
    assert out.stat().st_uid == 0


def test_the_sudo_user_is_read_from_both_variables(under_sudo: None) -> None:
    assert invoking_user() == (SUDO_USER_ID, SUDO_USER_ID)
