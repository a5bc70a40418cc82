"""Who ran rtloop through sudo: the one place that reads ``SUDO_UID`` and ``SUDO_GID``."""

from __future__ import annotations

import os
import re

_NUMBER = re.compile(r"[0-9]{1,10}")


def invoking_user() -> tuple[int, int] | None:
    """Running as root under sudo: the (uid, gid) of the user who ran sudo. None when not root, not under
    sudo, or when either variable is not a plain number (a garbled environment is believed in nothing)."""
    if os.geteuid() != 0:
        return None
    uid, gid = os.environ.get("SUDO_UID", ""), os.environ.get("SUDO_GID", "")
    if not (_NUMBER.fullmatch(uid) and _NUMBER.fullmatch(gid)):
        return None
    return int(uid), int(gid)


def trusted_uids() -> set[int]:
    """Whose files rtloop may run or talk to: root's, the caller's and, under sudo, those of the
    user who ran sudo (they could run anything as root already)."""
    uids = {0, os.geteuid()}
    invoker = invoking_user()
    if invoker is not None:
        uids.add(invoker[0])
    return uids


def trusted_users_phrase() -> str:
    """Who :func:`trusted_uids` trusts, in words: ``you (uid 1000) or root``; under sudo,
    ``you (uid 1001, via sudo) or root``."""
    invoker = invoking_user()
    if invoker is not None:
        return f"you (uid {invoker[0]}, via sudo) or root"
    return f"you (uid {os.geteuid()}) or root"
