"""App files (TOML) → :class:`~rtloop.app.App`. Every error names the file and the key.

    name = "jiwy"

    [tasks.plant]
    runnable = "jiwy_models:JiwyPlant"   # module beside the app file; or model = "20sim:models/Plant"
    args = {}                                  # keyword arguments of the constructor
    period_ns = 1_000_000
    priority = 80
    cpu = 1
    policy = "fifo"                            # fifo, rr, other, deadline
    overrun = "skip"                           # skip or catch_up
    watchdog_periods = 1000                    # stop the app if no cycle ends for this long (0: off)
    max_consecutive_misses = 5                 # stop the app after 5 misses in a row (absent: go on)

    [[connect]]
    from = "plant.y[0:2]"
    to = "controller.u[0:2]"

    [ports.setpoint]
    to = "controller.u[2:4]"                   # or source = "plant.y" for a port out of a task
    feed = "step.csv"                          # optional profile, relative to this file

    [record]
    signals = ["plant.y", "controller.y"]
"""

from __future__ import annotations

import importlib
import sys
import tomllib
from pathlib import Path
from typing import Any

from rtloop.app.builder import DEFAULT_WATCHDOG_PERIODS, App, parse_signal
from rtloop.errors import AppError, AppFileError, RtloopError
from rtloop.runnable import Runnable

TOP_KEYS = {
    "name": str, "description": str, "tasks": dict, "connect": list, "ports": dict, "record": dict, "ros": dict,
}
ROS_KEYS = {"domain_id": int, "publish": list, "subscribe": list}
ROS_TOPIC_KEYS = {
    "topic": str, "port": str, "source": str, "type": str, "qos": str, "joint_names": list, "every": int,
    "description": str,
}
TASK_KEYS = {
    "runnable": str, "model": str, "args": dict, "period_ns": int, "priority": int,
    "cpu": int, "policy": str, "overrun": str, "description": str, "watchdog_periods": int,
    "max_consecutive_misses": int,
}
PORT_KEYS = {
    "to": str, "source": str, "initial": list, "allow_nonfinite": bool, "capacity": int,
    "feed": str, "description": str,
}
CONNECT_KEYS = {"from": str, "to": str}
RECORD_KEYS = {"signals": list}
TYPE_NAMES = {str: "a string", int: "an integer", dict: "a table", list: "an array", bool: "true or false"}


def _check_keys(path: str, where: str, table: dict[str, Any], allowed: dict[str, type]) -> None:
    for key, value in table.items():
        full = f"{where}.{key}" if where else key
        if key not in allowed:
            close = [k for k in allowed if _similar(k, key)]
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise AppFileError(path, full, f"unknown key{hint}; expected one of {sorted(allowed)}")
        expected = allowed[key]
        if not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
            raise AppFileError(path, full, f"expected {TYPE_NAMES[expected]}, got {value!r}")


def _similar(a: str, b: str) -> bool:
    import difflib

    return difflib.SequenceMatcher(None, a, b).ratio() >= 0.75


def load_app(path: str | Path) -> App:
    """Read and validate an app file; builds the runnables (in this process)."""
    file = Path(path)
    shown = str(path)
    try:
        data = tomllib.loads(file.read_text())
    except FileNotFoundError:
        raise AppFileError(shown, "", "no such file") from None
    except tomllib.TOMLDecodeError as error:
        raise AppFileError(shown, "", f"not valid TOML: {error}") from None
    _check_keys(shown, "", data, TOP_KEYS)
    if "name" not in data:
        raise AppFileError(shown, "name", "missing; every app needs a name")
    if not data.get("tasks"):
        raise AppFileError(shown, "tasks", "missing; define at least one [tasks.NAME] table")
    base_dir = file.resolve().parent
    try:
        app = App(data["name"], source=shown)
    except AppError as error:
        raise AppFileError(shown, "name", str(error)) from None

    for task_name, table in data["tasks"].items():
        where = f"tasks.{task_name}"
        if not isinstance(table, dict):
            raise AppFileError(shown, where, "expected a table [tasks.NAME]")
        _check_keys(shown, where, table, TASK_KEYS)
        runnable = _build_runnable(shown, where, table, base_dir)
        if "period_ns" not in table:
            raise AppFileError(shown, f"{where}.period_ns", "missing; e.g. period_ns = 1_000_000 for 1 kHz")
        try:
            app.add_task(
                task_name, runnable, period_ns=table["period_ns"],
                priority=table.get("priority", 80), cpu=table.get("cpu"),
                policy=table.get("policy", "fifo"), overrun=table.get("overrun", "skip"),
                watchdog_periods=table.get("watchdog_periods", DEFAULT_WATCHDOG_PERIODS),
                max_consecutive_misses=table.get("max_consecutive_misses"),
            )
        except AppError as error:
            raise AppFileError(shown, where, str(error)) from None

    for index, table in enumerate(data.get("connect", [])):
        where = f"connect[{index}]"
        if not isinstance(table, dict):
            raise AppFileError(shown, where, "expected a table [[connect]] with from and to")
        _check_keys(shown, where, table, CONNECT_KEYS)
        for key in CONNECT_KEYS:
            if key not in table:
                raise AppFileError(shown, f"{where}.{key}", "missing")
        try:
            app.connect(parse_signal(table["from"], app, "from"), parse_signal(table["to"], app, "to"))
        except AppError as error:
            raise AppFileError(shown, where, str(error)) from None

    for port_name, table in data.get("ports", {}).items():
        where = f"ports.{port_name}"
        if not isinstance(table, dict):
            raise AppFileError(shown, where, "expected a table [ports.NAME]")
        _check_keys(shown, where, table, PORT_KEYS)
        try:
            app.port(
                port_name,
                to=parse_signal(table["to"], app, "to") if "to" in table else None,
                source=parse_signal(table["source"], app, "source") if "source" in table else None,
                initial=table.get("initial"),
                allow_nonfinite=table.get("allow_nonfinite", False),
                capacity=table.get("capacity", 4096),
                feed=(base_dir / table["feed"]) if "feed" in table else None,
            )
        except (AppError, TypeError, ValueError) as error:
            raise AppFileError(shown, where, str(error)) from None

    _load_ros(shown, data.get("ros", {}), app)

    record = data.get("record", {})
    _check_keys(shown, "record", record, RECORD_KEYS)
    for index, text in enumerate(record.get("signals", [])):
        try:
            app.record(parse_signal(str(text), app, "signal"))
        except AppError as error:
            raise AppFileError(shown, f"record.signals[{index}]", str(error)) from None
    return app


def _load_ros(shown: str, ros: dict[str, Any], app: App) -> None:
    """``[ros]``: ``domain_id`` and ``[[ros.publish]]`` / ``[[ros.subscribe]]`` tables."""
    _check_keys(shown, "ros", ros, ROS_KEYS)
    domain_id = ros.get("domain_id")
    for direction in ("publish", "subscribe"):
        for index, table in enumerate(ros.get(direction, [])):
            where = f"ros.{direction}[{index}]"
            if not isinstance(table, dict):
                raise AppFileError(shown, where, f"expected a table [[ros.{direction}]]")
            _check_keys(shown, where, table, ROS_TOPIC_KEYS)
            if "topic" not in table:
                raise AppFileError(shown, f"{where}.topic", "missing")
            if direction == "subscribe" and "port" not in table:
                raise AppFileError(shown, f"{where}.port", "missing: the input port the topic feeds")
            if direction == "subscribe" and ("joint_names" in table or "every" in table):
                raise AppFileError(shown, where, "joint_names and every apply to [[ros.publish]] only")
            options: dict[str, Any] = {"domain_id": domain_id}
            if "type" in table:
                options["msg_type"] = table["type"]
            if "qos" in table:
                options["qos"] = table["qos"]
            try:
                if direction == "publish":
                    source = parse_signal(table["source"], app, "source") if "source" in table else None
                    app.ros_publish(table["topic"], source=source, port=table.get("port"),
                                    joint_names=table.get("joint_names", ()), every=table.get("every", 1), **options)
                else:
                    app.ros_subscribe(table["topic"], port=table["port"], **options)
            except AppError as error:
                raise AppFileError(shown, where, str(error)) from None


def _build_runnable(shown: str, where: str, table: dict[str, Any], base_dir: Path) -> Runnable:
    has_runnable, has_model = "runnable" in table, "model" in table
    if has_runnable == has_model:
        raise AppFileError(shown, where, 'give exactly one of runnable = "module:Class" or model = "kind:path"')
    args = table.get("args", {})
    if has_model:
        try:
            from rtloop.models import load_model
        except ImportError as error:
            raise AppFileError(shown, f"{where}.model", f"model support unavailable: {error}") from None
        try:
            return load_model(table["model"], base_dir, **args)
        except (RtloopError, OSError, ValueError, TypeError) as error:  # incl. a model that does not build
            raise AppFileError(shown, f"{where}.model", str(error)) from None
    target = table["runnable"]
    module_name, _, class_name = target.partition(":")
    if not module_name or not class_name:
        raise AppFileError(shown, f"{where}.runnable", f'{target!r}: expected "module:Class"')
    if str(base_dir) not in sys.path:
        sys.path.insert(0, str(base_dir))  # task processes inherit sys.path (spawn)
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise AppFileError(
            shown, f"{where}.runnable",
            f"cannot import module {module_name!r} (looked beside the app file and on sys.path): {error}",
        ) from None
    cls = getattr(module, class_name, None)
    if cls is None:
        raise AppFileError(shown, f"{where}.runnable", f"module {module_name!r} has no {class_name!r}")
    try:
        runnable = cls(**args)
    except TypeError as error:
        raise AppFileError(shown, f"{where}.args", f"{target}({args}) failed: {error}") from None
    if not isinstance(runnable, Runnable):
        raise AppFileError(shown, f"{where}.runnable", f"{target} is not a subclass of rtloop.Runnable")
    return runnable
