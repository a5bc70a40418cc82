"""Start and stop the app's ROS 2 bridge processes (non-real-time) alongside a run.

Each ``[[ros.publish]]`` / ``[[ros.subscribe]]`` entry gets a process of its own running
:func:`rtloop.ros.bridge.bridge_process_main`, attached to the app's ports by the
registry file. A bridge that fails or is killed never stops the real-time tasks: its
fate is reported in ``summary.json`` under ``bridges``.
"""

from __future__ import annotations

import importlib.util
import multiprocessing
import signal
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rtloop.app.builder import App
from rtloop.app.byvalue import children_without_main
from rtloop.app.specs import RosTopic

STOP_TIMEOUT_S = 5.0
READY_WITHIN_S = 10.0
"""How long T0 waits for the bridges to have their DDS entity (they import DDS; the tasks, forked
from the task server, are ready in ms): then the run starts anyway, a late bridge catches up."""


def dds_available() -> str:
    """'' if a ROS 2 backend can be used here, else why not."""
    if importlib.util.find_spec("cyclonedds") or importlib.util.find_spec("rclpy"):
        return ""
    return "ROS 2 bridges are off: neither cyclonedds nor rclpy is installed (pip install 'rtloop[ros]')"


def discovery_warning() -> str:
    """'' unless ROS 2's discovery variables were not taken as written (the bridges inherit them)."""
    from rtloop.ros.discovery import discovery_from_env

    return discovery_from_env().warning


@dataclass
class _Bridge:
    topic: RosTopic
    process: Any
    pipe: Any
    stats: dict[str, Any] = field(default_factory=dict)
    error: str = ""
    ready: bool = False


class Bridges:
    """The bridge processes of one run."""

    def __init__(self, app: App) -> None:
        self.app = app
        self.running: list[_Bridge] = []
        self.off_reason = dds_available() if app.ros_topics else ""
        self.note = (self.off_reason or discovery_warning()) if app.ros_topics else ""

    def start(self, registry_path: Path) -> None:
        if not self.app.ros_topics or self.off_reason:
            return
        from rtloop.ros.bridge import bridge_process_main

        context = multiprocessing.get_context("spawn")
        for topic in self.app.ros_topics:
            reader, writer = context.Pipe(duplex=False)
            process = context.Process(
                target=bridge_process_main, args=(topic, str(registry_path), writer),
                name=f"rtloop-{self.app.name}-bridge-{topic.topic}", daemon=True,
            )
            with children_without_main():  # a bridge needs nothing of __main__ (a notebook, python -)
                process.start()
            writer.close()
            self.running.append(_Bridge(topic, process, reader))

    def poll(self) -> None:
        for bridge in self.running:
            try:
                while bridge.pipe.poll():
                    message = bridge.pipe.recv()
                    if message.get("kind") == "ready":
                        bridge.ready = True
                    elif message.get("kind") == "stats":
                        bridge.stats = message
                    elif message.get("kind") == "error":
                        bridge.error = message.get("reason", "unknown error")
            except (EOFError, OSError):
                pass

    def starting(self) -> bool:
        """Whether a bridge is still on its way to its DDS entity (alive, not failed, not ready)."""
        self.poll()
        return any(not b.ready and not b.error and b.process.is_alive() for b in self.running)

    def stop(self) -> None:
        for bridge in self.running:
            if bridge.process.is_alive():
                bridge.process.terminate()  # SIGTERM: the bridge sends its last stats and leaves
        for bridge in self.running:
            bridge.process.join(STOP_TIMEOUT_S)
            if bridge.process.is_alive():
                bridge.process.kill()
                bridge.process.join()
        self.poll()

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for bridge in self.running:
            exitcode = bridge.process.exitcode
            stopped_cleanly = exitcode in (0, -signal.SIGTERM)
            state = "ok" if stopped_cleanly and not bridge.error else "failed"
            reason = bridge.error or ("" if stopped_cleanly else f"bridge process ended with {exitcode}")
            key = f"{bridge.topic.direction} {bridge.topic.topic}"
            out[key] = {"port": bridge.topic.port, "type": bridge.topic.msg_type, "state": state,
                        "reason": reason, **{k: v for k, v in bridge.stats.items() if k != "kind"}}
        return out
