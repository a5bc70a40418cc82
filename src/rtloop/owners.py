"""Who may write a file besides its owner: through its mode, its group (every member, from the user
and group databases) or an access ACL. The trust checks of code, models and caches ask here."""

from __future__ import annotations

import grp
import os
import pwd
import stat
import struct
from pathlib import Path


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


def untrusted_writer(facts: os.stat_result, trusted: set[int], whom: str, target: Path | int) -> str | None:
    """Who other than a trusted user may write ``target`` (a path or descriptor with these facts; None: nobody)."""
    if facts.st_mode & stat.S_IWOTH:
        return "writable by every user"
    if facts.st_mode & stat.S_IWGRP:  # with an access ACL these bits are its mask: ask the ACL too
        if not group_members(facts.st_gid) <= trusted:
            return f"writable by group {facts.st_gid}, whose members are not all {whom}"
        others = sorted(_acl_writers(target) - trusted)
        if others:
            return f"writable through an ACL by uid {others[0]} (getfacl shows it), not only by {whom}"
    return None


_ACL_USER, _ACL_GROUP, _ACL_MASK = 0x02, 0x08, 0x10  # tags of the kernel's posix_acl_access xattr
_ACL_WRITE = 0x02


def folder_problem(folder: Path, trusted: set[int], whom: str, *,
                   sticky_is_enough: bool) -> tuple[Path, str, bool] | None:
    """Why a user not trusted could change what ``folder`` holds (None: none can), as (the folder,
    what it is, whether ``chmod go-w`` is the fix): it or a folder
    above it is theirs, or one they may write to. Above it a sticky folder such as /tmp is fine
    (nobody renames or removes there what they do not own); for ``folder`` itself only when
    ``sticky_is_enough`` (code read from it), not where rtloop writes: in a sticky folder another
    user may still add a name, a link rtloop would write through."""
    for path in (folder, *folder.parents):
        facts = os.stat(path)
        if facts.st_uid not in trusted:
            return path, f"owned by uid {facts.st_uid}, not by {whom}", False
        writer = untrusted_writer(facts, trusted, whom, path)
        sticky = facts.st_mode & stat.S_ISVTX and (path != folder or sticky_is_enough)
        if writer and not sticky:
            return path, writer, True
    return None


def output_folder_problem(out: Path) -> str | None:
    """Why rtloop must not write into ``out`` (None: it may): another user could plant a link there
    (or swap the folder) for a write of this process to follow — as root, onto any file. ``out``
    need not exist yet: then the folders above it are checked (made here, it is this user's)."""
    from rtloop.sudo import trusted_uids, trusted_users_phrase

    trusted = trusted_uids()
    whom = trusted_users_phrase()
    absolute = Path(os.path.abspath(out))
    for path in (*reversed(absolute.parents), absolute):  # a link on the way: whose is it?
        try:
            facts = os.lstat(path)
        except FileNotFoundError:
            break
        if stat.S_ISLNK(facts.st_mode) and facts.st_uid not in trusted:
            return f"{path} is a symbolic link owned by uid {facts.st_uid}, not by {whom}"
    existing = next(p for p in (absolute, *absolute.parents) if p.exists())
    problem = folder_problem(existing.resolve(), trusted, whom, sticky_is_enough=existing != absolute)
    if problem is None:
        return None
    path, what, chmod_fixes = problem
    return (f"{path} is {what}: another user could put a link there for rtloop to write through"
            + (f" (chmod go-w {path})" if chmod_fixes else ""))


def _acl_writers(target: Path | int) -> set[int]:
    """The uids an access ACL lets write ``target`` (named users, members of named groups); none without one."""
    try:
        raw = os.getxattr(target if isinstance(target, int) else os.fspath(target), "system.posix_acl_access")
    except OSError:
        return set()  # no ACL, or a file system without them
    entries = [struct.unpack_from("<HHI", raw, offset) for offset in range(4, len(raw) - 7, 8)]
    mask = next((perm for tag, perm, _ in entries if tag == _ACL_MASK), 7)
    writers: set[int] = set()
    for tag, perm, ident in entries:
        if perm & mask & _ACL_WRITE:
            if tag == _ACL_USER:
                writers.add(ident)
            elif tag == _ACL_GROUP:
                writers |= group_members(ident)
    return writers
