"""summary.json is synced to the disk at the start and the end of a run, not at every rewrite while it runs.

Each fsync of a rewrite forced a journal commit and a disk cache flush every 2 s, whose completion
interrupts landed on the task's CPU where the disk's interrupt is bound to it (issue 33). The page
cache keeps an unsynced summary through a crash of any rtloop process; a filesystem that may commit
a rename before the renamed file's data is still synced at every rewrite.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

import rtloop
from conftest import unique_name
from rt_test_runnables import Counter
from rtloop.record import summary as summary_module
from rtloop.record.summary import SummaryFile, rename_orders_data
from rtloop.runtime.session import Limits

MOUNTINFO = """\
22 1 254:0 / / rw,relatime shared:1 - ext4 /dev/vda rw,discard
23 22 0:21 / /proc rw,nosuid shared:2 - proc proc rw
24 22 0:22 / /dev/shm rw,nosuid,nodev shared:3 - tmpfs tmpfs rw
25 22 254:16 / /data rw,relatime shared:4 - xfs /dev/vdb rw,attr2
26 22 254:32 / /fast rw,relatime shared:5 - ext4 /dev/vdc rw,noauto_da_alloc
27 22 254:48 / /wb rw,relatime shared:6 - ext4 /dev/vdd rw,data=writeback
28 25 0:40 / /data/in\\040ram rw shared:7 - tmpfs tmpfs rw
"""


@pytest.mark.parametrize(("folder", "orders"), [
    ("/home/me/runs/a", True),  # ext4 with its defaults
    ("/dev/shm/runs", True),  # tmpfs: a power cut takes everything anyway
    ("/data/runs", False),  # xfs: a rename may be committed before the data
    ("/data/in ram/runs", True),  # the mount on top wins
    ("/fast/runs", False),  # ext4 told not to write a replaced file's data first
    ("/wb/runs", False),  # ext4 without data ordering
    ("/datax/runs", True),  # /data is not a prefix of /datax: the root's ext4
])
def test_which_filesystems_keep_a_renamed_file_whole_without_a_sync(folder: str, orders: bool, monkeypatch) -> None:
    monkeypatch.setattr(Path, "resolve", lambda self: self)  # the folders exist in MOUNTINFO only
    assert rename_orders_data(Path(folder), MOUNTINFO) is orders


def test_an_unreadable_mount_table_means_every_summary_is_synced(tmp_path: Path) -> None:
    assert rename_orders_data(tmp_path, "garbage\n") is False


class Summary:  # what SummaryFile.write asks of a summary
    def __init__(self, n: int) -> None:
        self.n = n

    def to_json(self) -> dict[str, int]:
        return {"n": self.n}


@pytest.fixture
def fsyncs(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The summaries synced (other files a run syncs at its end, metadata.yaml, are left out)."""
    calls: list[str] = []
    real = os.fsync

    def counting(fd: int) -> None:
        name = os.readlink(f"/proc/self/fd/{fd}")
        if "summary" in Path(name).name:
            calls.append(name)
        real(fd)

    monkeypatch.setattr(os, "fsync", counting)
    return calls


def test_the_first_and_the_durable_summaries_are_synced_the_running_ones_not(tmp_path: Path, fsyncs,
                                                                              monkeypatch) -> None:
    monkeypatch.setattr(summary_module, "rename_orders_data", lambda folder: True)
    summary = SummaryFile(tmp_path)
    assert summary.write(Summary(1), durable=False) and len(fsyncs) == 1  # the first: a file to find at all
    assert summary.write(Summary(2), durable=False) and len(fsyncs) == 1
    assert json.loads((tmp_path / "summary.json").read_text()) == {"n": 2}  # written all the same
    assert summary.write(Summary(3)) and len(fsyncs) == 2  # the final one
    assert sorted(p.name for p in tmp_path.iterdir()) == [".summary-reserve", "summary.json"]


def test_every_summary_is_synced_where_a_rename_may_come_before_the_data(tmp_path: Path, fsyncs,
                                                                         monkeypatch) -> None:
    monkeypatch.setattr(summary_module, "rename_orders_data", lambda folder: False)
    summary = SummaryFile(tmp_path)
    for n in range(3):
        assert summary.write(Summary(n), durable=False)
    assert len(fsyncs) == 3


def test_a_run_syncs_its_summary_twice_however_often_it_rewrites_it(tmp_path: Path, fsyncs, monkeypatch) -> None:
    monkeypatch.setattr(summary_module, "rename_orders_data", lambda folder: True)
    rewrites: list[bool] = []
    real_write = SummaryFile.write

    def counted(self: SummaryFile, summary: object, *, durable: bool = True) -> bool:
        rewrites.append(durable)
        return real_write(self, summary, durable=durable)  # type: ignore[arg-type]

    monkeypatch.setattr(SummaryFile, "write", counted)
    app = rtloop.App(unique_name("sync"))
    app.add_task("count", Counter(), period_ns=1_000_000, policy="other")
    out = tmp_path / "run"
    rtloop.run(app, 1.0, out, limits=Limits(summary_interval_s=0.1))
    assert rewrites.count(False) >= 4 and rewrites[-1] is True, rewrites
    assert len(fsyncs) == 2, (fsyncs, rewrites)  # the first summary and the final one
    assert json.loads((out / "summary.json").read_text())["running"] is False
