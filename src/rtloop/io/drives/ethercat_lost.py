"""A bounded tolerance for cycles whose EtherCAT frame does not come back in time (``lost_frames_max``).

A cycle's LRW frame that is not back within ``timeout_us`` of its send (lost on the wire, or late:
a host stall between the send and the receive, a slave's answer delayed) is, by default, a fault at
the first (``lost_frames_max = 0``). With ``lost_frames_max = N`` up to N such cycles in a row are
a *lost frame* each, as a CAN frame with ``on_missing = "stale"`` is a stale read:

- the readings are not taken: each keeps the value of the last frame that came, and the device's
  ``frame_ok`` reading is 0 for that cycle (1 when the frame came), for a task to wire;
- the cycle is counted (the device's stale reads: summary.json ``devices.NAME``, with the cycles
  they happened at, the longest run in a row, and the run's notes); the replay plays the readings
  back as the run read them;
- the next cycle's commands go out as usual, in a frame with the next datagram index: an answer to
  an earlier frame that comes after its cycle is passed over (its index is not the awaited one), never
  taken as a later cycle's;
- N + 1 in a row is the fault it is without the key: the drives are brought to quick stop; so are
  lost frames in a row whose sends span more periods than N frames' do (a host stall skipped
  releases between them: the drives went longer without the master than N periods).

A frame that comes back in time with a wrong working counter is not a lost frame: the network
carried it, and a slave did not exchange (out of OP, lost): that does not heal by itself in a few
cycles, and its drive is already stopping; it stays a fault at once.

The bound. While frames are lost nobody watches the drives but the drives themselves and their
slaves' SM watchdog (``watchdog_ms``): (N + 1) periods must stay within the watchdog (else a slave
leaves OP during a loss the run tolerates, and its drive stops without the master saying why) and
within 100 ms; with a ``timeout_us`` past the period, N periods plus those the timeout spans (the
next frame waits for the last lost one's timeout). N is also below 255: the datagram index (one
byte, one step per cycle) tells a late answer from the awaited one only among fewer than 256
frames in flight.
"""

from __future__ import annotations

__all__ = ["BLIND_MAX_NS", "INDEX_FRAMES", "blind_bound_problem", "lost_frames_fault", "lost_frames_note",
           "lost_frames_span", "waits_in_periods"]

BLIND_MAX_NS = 100_000_000
"""The longest the drives may run unwatched by the master, whatever the SM watchdog allows."""
INDEX_FRAMES = 255
"""Frames in flight the one-byte datagram index tells apart from the awaited one."""


def waits_in_periods(timeout_ns: int, period_ns: int) -> int:
    """The periods a lost frame's cycle takes: it waits ``timeout_us`` for the answer, so with a
    timeout past the period the next frame goes out only at the release after it (1 below)."""
    return max(1, -(-timeout_ns // period_ns)) if period_ns > 0 else 1


def blind_bound_problem(lost_frames_max: int, period_ns: int, watchdog_ms: float, timeout_ns: int = 0) -> str | None:
    """What is wrong with ``lost_frames_max`` at this period, SM watchdog and ``timeout_us``
    (``timeout_ns``) (one phrase), or None. The drives go without the master from the last frame
    that came to the next one: N lost frames' periods, and the last one's wait for its answer (one
    period, or more where the timeout is past the period: the next frame waits for it)."""
    if lost_frames_max <= 0:
        return None
    if lost_frames_max >= INDEX_FRAMES:
        return (f"{lost_frames_max} is too many: at most {INDEX_FRAMES - 1} (the datagram index tells a late answer "
                f"from the awaited one among {INDEX_FRAMES + 1} frames)")
    waits = waits_in_periods(timeout_ns, period_ns)
    blind_ns = (lost_frames_max + waits) * period_ns
    watchdog_ns = round(watchdog_ms * 1e6)
    limit_ns = min(watchdog_ns, BLIND_MAX_NS)
    if blind_ns < limit_ns:
        return None
    which = f"the slaves' SM watchdog, watchdog_ms = {watchdog_ms:g}" if watchdog_ns <= BLIND_MAX_NS else \
        "the bound on running the drives blind"
    # the largest N: (N + waits) periods below the limit
    most = min(INDEX_FRAMES - 1, max(0, -(-limit_ns // period_ns) - 1 - waits))
    late = "" if waits == 1 else (f" (timeout_us = {timeout_ns / 1e3:g} µs is past the period: a lost frame's cycle "
                                  f"takes {waits} periods)")
    return (f"{lost_frames_max} lost frames in a row at the task's period of {period_ns / 1e6:g} ms{late} leave the "
            f"drives unwatched for {blind_ns / 1e6:g} ms, not less than {limit_ns / 1e6:g} ms ({which}): at most "
            f"{most}" + ("" if most or waits == 1 else ", or a timeout_us below the period"))


def lost_frames_span(since_first_s: float, period_ns: int) -> int:
    """How many lost frames in a row a run of them counts for: the periods from the first lost
    frame's send to this one's, plus this one (rounded: the releases' jitter aside); 0 when the
    period is not known."""
    return int(since_first_s * 1e9 / period_ns + 0.5) + 1 if period_ns > 0 else 0


def lost_frames_fault(where: str, in_a_row: int, timeout_us: float, lost_frames_max: int, spans: int = 0) -> str:
    """The fault of the cycle whose lost frame is one too many (``spans``: the periods the lost frames
    in a row took, counting this one)."""
    if lost_frames_max <= 0:
        return (f"{where}: the LRW frame did not come back within {timeout_us:.0f} µs (timeout_us): a slave lost, "
                "a cable pulled, or the frame lost (a dropped frame, a stalled or busy host: lost_frames_max lets "
                "a few in a row pass, docs/drives.md)")
    over = f" over {spans} periods (releases skipped between them)" if spans > in_a_row else ""
    return (f"{where}: the LRW frame did not come back within {timeout_us:.0f} µs (timeout_us), {in_a_row} cycles in "
            f"a row{over} (lost_frames_max = {lost_frames_max}): a slave lost, a cable pulled, or the host stalled")


def lost_frames_note(lost: int, longest: int, lost_frames_max: int, timeout_us: float) -> str:
    """The run's note on its lost frames (empty when the key is not set)."""
    if lost_frames_max <= 0:
        return ""
    return (f"{lost} cycle{'' if lost == 1 else 's'} whose LRW frame did not come back within {timeout_us:.0f} µs "
            f"(lost frames: readings held, frame_ok 0), at most {longest} in a row (lost_frames_max = "
            f"{lost_frames_max})")
