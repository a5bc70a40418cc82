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
