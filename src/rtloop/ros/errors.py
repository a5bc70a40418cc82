"""Errors of the ROS 2 bridge, and the checks that raise them.

Nothing here imports ``cyclonedds`` or ``rclpy``: these checks run precisely when
they may be missing.
"""

from __future__ import annotations

import importlib
import os
import platform

from rtloop.errors import RtloopError

CYCLONEDDS_HINT = (
    "install it with: pip install 'rtloop[ros]'. "
    "There is no cyclonedds wheel for aarch64 (Raspberry Pi) on PyPI; there, install "
    "ROS 2, source its setup.bash and use the rclpy backend (backend='rclpy')."
)
RCLPY_HINT = (
    "rclpy comes with a ROS 2 install, not from pip: install ROS 2 "
    "(https://docs.ros.org), then `source /opt/ros/<distro>/setup.bash` before starting "
    "rtloop. Without ROS 2, use backend='cyclonedds' (pip install 'rtloop[ros]')."
)

# ROS 2 uses domain ids 0..101 by default and DDS allows up to 232 on Linux.
MAX_DOMAIN_ID = 232


class RosUnavailable(RtloopError, ImportError):
    """The DDS library a ROS 2 backend needs (cyclonedds or rclpy) cannot be imported."""


class RosConfigError(RtloopError, ValueError):
    """A topic name, QoS preset, domain id or message type for ROS 2 is invalid."""


def has_module(name: str) -> bool:
    """Return whether ``name`` imports (an installed package whose library fails to load
    counts as missing)."""
    try:
        importlib.import_module(name)
    except (ImportError, OSError):
        return False
    return True


def require_cyclonedds() -> None:
    """Raise :class:`RosUnavailable` with install instructions if cyclonedds is missing."""
    if not has_module("cyclonedds"):
        machine = platform.machine()
        raise RosUnavailable(f"the Python package 'cyclonedds' is not installed ({machine}); "
                             + CYCLONEDDS_HINT)


def require_rclpy() -> None:
    """Raise :class:`RosUnavailable` explaining how to get rclpy if it is missing."""
    if not has_module("rclpy"):
        raise RosUnavailable("the rclpy backend was requested but rclpy is not importable; "
                             + RCLPY_HINT)


def choose_backend(backend: str) -> str:
    """Resolve ``"auto"``, ``"cyclonedds"`` or ``"rclpy"`` to an available backend.

    ``"auto"`` prefers cyclonedds (no ROS 2 install needed) and falls back to rclpy.

    Raises:
        RosConfigError: ``backend`` is not one of the three names.
        RosUnavailable: the requested backend (or, for ``"auto"``, either) is missing.
    """
    if backend == "auto":
        if has_module("cyclonedds"):
            return "cyclonedds"
        if has_module("rclpy"):
            return "rclpy"
        raise RosUnavailable("neither cyclonedds nor rclpy is importable; " + CYCLONEDDS_HINT)
    if backend == "cyclonedds":
        require_cyclonedds()
        return backend
    if backend == "rclpy":
        require_rclpy()
        return backend
    raise RosConfigError(f"unknown ROS backend {backend!r}: expected 'auto', 'cyclonedds' "
                         "or 'rclpy'")


def domain_id_from_env(domain_id: int | None = None) -> int:
    """Return ``domain_id``, or ``ROS_DOMAIN_ID`` from the environment, or 0 as ROS 2 does.

    Raises:
        RosConfigError: the id (or the environment variable) is not an integer in
            0..232.
    """
    source = "domain_id"
    if domain_id is None:
        text = os.environ.get("ROS_DOMAIN_ID", "").strip()
        if not text:
            return 0
        source = f"ROS_DOMAIN_ID={text!r}"
        try:
            domain_id = int(text)
        except ValueError:
            raise RosConfigError(f"{source}: expected an integer 0..{MAX_DOMAIN_ID}") from None
    if not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise RosConfigError(f"{source}: {domain_id} is outside 0..{MAX_DOMAIN_ID}")
    return domain_id
