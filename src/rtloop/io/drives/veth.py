"""A veth pair for the emulated EtherCAT drives: the master's end and the emulator's, up, and gone
again afterwards (``ip link``, needs root or CAP_NET_ADMIN).

The drive tests, ``benchmarks/bench_ethercat_drives.py`` and a person trying the example all need
the same two links::

    with veth_pair("ecm0", "ecs0"):
        ...  # rtloop io emulate ethercat --interface ecs0 ... ; rtloop run (interface = "ecm0")
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["VethError", "delete_veth", "make_veth", "veth_pair", "veth_problem"]


class VethError(OSError):
    """The veth pair could not be made (one line: what ``ip`` said)."""


def veth_problem() -> str | None:
    """Why a veth pair cannot be made here (None: it may be)."""
    if os.geteuid() != 0:
        return "needs root (a veth pair: ip link add; raw sockets on it)"
    if shutil.which("ip") is None:
        return "needs the ip command (iproute2) to make a veth pair"
    return None


def make_veth(master: str, slave: str) -> None:
    """``ip link add MASTER type veth peer name SLAVE``, both set up; VethError says why not."""
    problem = veth_problem()
    if problem:
        raise VethError(problem)
    made = subprocess.run(["ip", "link", "add", master, "type", "veth", "peer", "name", slave],
                          capture_output=True, text=True)
    if made.returncode != 0:
        raise VethError(f"cannot make the veth pair {master}/{slave}: {made.stderr.strip()}")
    for name in (master, slave):
        up = subprocess.run(["ip", "link", "set", name, "up"], capture_output=True, text=True)
        if up.returncode != 0:
            delete_veth(master)
            raise VethError(f"cannot set {name} up: {up.stderr.strip()}")


def delete_veth(master: str) -> None:
    """Delete the pair (deleting one end deletes both); quiet when it is gone already."""
    subprocess.run(["ip", "link", "del", master], capture_output=True)


@contextmanager
def veth_pair(master: str, slave: str) -> Iterator[tuple[str, str]]:
    """The pair ``(master, slave)``, up, for the ``with`` block; deleted afterwards."""
    make_veth(master, slave)
    try:
        yield master, slave
    finally:
        delete_veth(master)
