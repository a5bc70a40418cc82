"""The suite's own parallel run (pytest-xdist, tests/conftest.py): a test marked ``alone`` runs with no
other test of the run beside it, ordinary tests run side by side, and a serial run takes no lock."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from conftest import alone_lock_folder, machine_share


class Holder(threading.Thread):
    """A test of another worker: holds the run's lock (as ``machine_share`` takes it) until released."""

    def __init__(self, folder: Path, alone: bool) -> None:
        super().__init__(daemon=True)
        self.folder, self.alone = folder, alone
        self.entered, self.release = threading.Event(), threading.Event()

    def run(self) -> None:
        with machine_share(self.folder, self.alone):
            self.entered.set()
            self.release.wait(60)

    def done(self) -> None:
        self.release.set()
        self.join(60)


def started(folder: Path, alone: bool) -> Holder:
    holder = Holder(folder, alone)
    holder.start()
    return holder


def test_ordinary_tests_run_side_by_side(tmp_path: Path) -> None:
    first, second = started(tmp_path, alone=False), started(tmp_path, alone=False)
    assert first.entered.wait(10) and second.entered.wait(10)
    first.done()
    second.done()


def test_an_alone_test_waits_for_the_running_test_and_the_next_one_waits_for_it(tmp_path: Path) -> None:
    running = started(tmp_path, alone=False)
    assert running.entered.wait(10)
    alone = started(tmp_path, alone=True)
    assert not alone.entered.wait(0.3), "an alone test started beside a running test"
    following = started(tmp_path, alone=False)  # asks after the alone test: queued behind it, not beside
    assert not following.entered.wait(0.3), "a test overtook the waiting alone test"
    running.done()
    assert alone.entered.wait(10)
    assert not following.entered.wait(0.3), "a test started beside an alone test"
    alone.done()
    assert following.entered.wait(10)
    following.done()


def test_a_serial_run_takes_no_lock(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("PYTEST_XDIST_WORKER", raising=False)
    assert alone_lock_folder(request.config) is None
    with machine_share(None, alone=True), machine_share(None, alone=True):  # would wait forever if it locked
        pass
