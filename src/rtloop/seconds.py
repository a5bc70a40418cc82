"""Times written as decimal seconds that read back to the nanosecond.

``t_ns / 1e9`` is a float: its shortest text stops telling neighbouring nanoseconds apart once
the seconds need more digits than a double holds (from 2^53 ns, 104 days, a row comes back a
nanosecond off; further on, several), and device playback then finds no release at that time.
An integer number of nanoseconds has an exact decimal text; these two functions write and read
it without going through a float.
"""

from __future__ import annotations

from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation

NS_PER_S = 1_000_000_000


def seconds_text(t_ns: int) -> str:
    """``t_ns`` as seconds, exactly: ``0.0``, ``0.01``, ``1157407.407407407`` (up to nine decimals)."""
    sign = "-" if t_ns < 0 else ""
    seconds, ns = divmod(abs(t_ns), NS_PER_S)
    return f"{sign}{seconds}.{f'{ns:09d}'.rstrip('0') or '0'}"


def ns_from_seconds(text: str) -> int:
    """The nanoseconds of a decimal number of seconds, read exactly (the nearest one for more than nine
    decimals); the shortest text of a float, as files of earlier versions hold, reads as that float's value.

    Raises ValueError for text that is not a finite number."""
    try:
        value = Decimal(text.strip())
    except InvalidOperation:
        raise ValueError(f"not a number of seconds: {text!r}") from None
    if not value.is_finite():
        raise ValueError(f"not a finite number of seconds: {text!r}")
    return int(value.scaleb(9).to_integral_value(ROUND_HALF_EVEN))
