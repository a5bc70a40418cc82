"""The start-up allowance of task processes: 30 s, or RTLOOP_STARTUP_ALLOWANCE_S where start-up is slow."""

from __future__ import annotations

import pytest

from rtloop.errors import AppError
from rtloop.runtime import supervisor


def test_the_allowance_is_30_s_unless_the_environment_gives_seconds(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(supervisor.STARTUP_ALLOWANCE_ENV, raising=False)
    assert supervisor.startup_allowance_s(30.0) == 30.0
    monkeypatch.setenv(supervisor.STARTUP_ALLOWANCE_ENV, "600")
    assert supervisor.startup_allowance_s(30.0) == 600.0


@pytest.mark.parametrize("text", ["", "soon", "nan", "inf", "0", "-5", "1e308"])
def test_a_bad_allowance_is_one_line_naming_the_variable(monkeypatch: pytest.MonkeyPatch, text: str) -> None:
    monkeypatch.setenv(supervisor.STARTUP_ALLOWANCE_ENV, text)
    with pytest.raises(AppError, match=r"RTLOOP_STARTUP_ALLOWANCE_S=.*a number of seconds from 1 to 3600") as caught:
        supervisor.startup_allowance_s(30.0)
    assert "\n" not in str(caught.value)


def test_where_start_up_is_declared_slow_t0_lies_further_after_the_last_ready(
    monkeypatch: pytest.MonkeyPatch, tmp_path
) -> None:
    # T0's margin covers a task's way from seeing T0 to its first release; where start-up is
    # 20 times slower (the emulated guest: 600 s), so is that way.
    from rt_test_runnables import Noop
    from rtloop import App

    app = App(f"margin_{id(tmp_path)}")
    app.add_task("t", Noop(), period_ns=1_000_000, policy="other")
    default_ns = supervisor.DEFAULT_LIMITS.start_margin_ns
    monkeypatch.delenv(supervisor.STARTUP_ALLOWANCE_ENV, raising=False)
    assert supervisor.Supervisor(app, 1.0, tmp_path / "a", trim=0).limits.start_margin_ns == default_ns
    monkeypatch.setenv(supervisor.STARTUP_ALLOWANCE_ENV, "600")
    slow = supervisor.Supervisor(app, 1.0, tmp_path / "b", trim=0).limits
    assert (slow.startup_allowance_s, slow.start_margin_ns) == (600.0, 20 * default_ns)
    monkeypatch.setenv(supervisor.STARTUP_ALLOWANCE_ENV, "5")  # a faster machine keeps the margin
    assert supervisor.Supervisor(app, 1.0, tmp_path / "c", trim=0).limits.start_margin_ns == default_ns
