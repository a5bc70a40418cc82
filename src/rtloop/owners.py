"""Who may write a file through its group: every member of a group, from the user and group databases."""

from __future__ import annotations

import grp
import pwd


def group_members(gid: int) -> set[int]:
    """Every uid in group ``gid``: listed members and users whose primary group it is. A group
    unknown here may hold anyone: it answers with a uid no trusted set contains."""
    try:
        names = grp.getgrgid(gid).gr_mem
    except KeyError:
        return {-1}
    members = {user.pw_uid for user in pwd.getpwall() if user.pw_gid == gid}
    for name in names:
        try:
            members.add(pwd.getpwnam(name).pw_uid)
        except KeyError:
            members.add(-1)
    return members
