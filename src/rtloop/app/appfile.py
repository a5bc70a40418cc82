"""App files (TOML) → :class:`~rtloop.app.App`. Every error names the file and the key.

    name = "jiwy"

    [tasks.plant]
    runnable = "jiwy_models:JiwyPlant"   # module beside the app file; or model = "20sim:models/Plant"
    args = {}                                  # keyword arguments of the constructor
    parameters = {}                            # parameters by name (FMU, 20-sim, a Runnable's live ones);
                                               # 20-sim's pan\\r is written pan.r: { pan.r = 0.018 }
    period_ns = 1_000_000
    priority = 80
    cpu = 1
    policy = "fifo"                            # fifo, rr, other, deadline
    overrun = "skip"                           # skip or catch_up
    watchdog_periods = 1000                    # stop the app if no cycle ends for this long (0: off)
    max_consecutive_misses = 5                 # stop the app after 5 misses in a row (absent: go on)
    lock_blas_buffer = false                   # true: lock OpenBLAS's 32 MB buffer too (large matrix products)
    units = { AnglePan = "rad", "u[0]" = "V" } # units of signals, by name or index (over the model's own)

    [devices.motor]                            # hardware the task "controller" reads and writes
    kind = "serial"                            # gpio, can, spi, serial, i2c (their settings follow)
    task = "controller"                        # runs in that task's process, at its period
    io = "let"                                 # commands written at t + P (default), or "immediate"
    twin = "motor_model:MotorDriverTwin"       # answers as the device does, in rtloop simulate
    port = "/dev/ttyUSB0"                      # ... the kind's own settings
    [devices.motor.limits.voltage]             # per command: clamp, rate limit, safe value
    min = -12.0
    max = 12.0
    safe = 0.0
    rate_per_s = 2400.0

    [[connect]]
    from = "plant.y[0:2]"
    to = "controller.u[0:2]"

    [ports.setpoint]
    to = "controller.u[2:4]"                   # or source = "plant.y" for a port out of a task
    initial = [0.0, 0.0]                       # what the task reads until the first write (default: 0)
    feed = "step.csv"                          # optional profile, relative to this file: t_s, then one
                                               # column per value; each row holds until the next
    nudge = "offset"                           # with a feed, live writes add to it ("override": a write
                                               # holds until the next row); without nudge they are refused
    range = [-1.0, 1.0]                        # writes outside it are refused and counted (or value_range);
                                               # [[0.0, 0.5], [0.0, 20.0]]: one [lo, hi] per value

    [record]
    signals = ["plant.y", "controller.y"]

    [[plot]]                                   # optional: these signals on one axis of the report
    title = "pan"
    signals = ["controller.SetPointPan", "plant.AnglePan"]

    [ros]                                      # optional; domain_id defaults to ROS_DOMAIN_ID or 0
    [[ros.publish]]
    topic = "/jiwy/angles"
    source = "plant.y[0:2]"                    # or port = "NAME" (an output port)
    type = "sensor_msgs/msg/JointState"
    qos = "reliable"                           # default: ROS 2's default profile, matches every
                                               # reader; "sensor" = best effort (best-effort readers only)
    [[ros.subscribe]]
    topic = "/jiwy/setpoint"
    port = "setpoint"

    [foxglove]                                 # optional: a live view (pip install 'rtloop[live]')
    port = 8765                                # ws://127.0.0.1:8765 ; host = "0.0.0.0" to serve the network
    inputs = ["setpoint"]                      # input ports Foxglove may publish to (default: none)
"""

from __future__ import annotations

import importlib
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rtloop.app import sources
from rtloop.app.builder import App, parse_signal
from rtloop.app.modules import ModuleRefused, check_model_files, installed_origin, load_module_file, module_beside
from rtloop.app.specs import DEFAULT_WATCHDOG_PERIODS, MAX_TASKS, too_many_tasks
from rtloop.errors import AppError, AppFileError, DeviceError, RtloopError
from rtloop.io.device import build_device, device_class
from rtloop.runnable import Runnable
from rtloop.switching import Controllers
from rtloop.text import clip, shorten

MAX_APP_FILE_BYTES = 1 << 20
MAX_NESTING_LEVELS = 32
"""Tables and arrays inside one another: an app file needs about 6 (devices.drive.send[0].signals[0])."""

TOP_KEYS = {
    "name": str, "description": str, "tasks": dict, "connect": list, "ports": dict, "record": dict, "ros": dict,
    "foxglove": dict, "devices": dict, "plot": list,
}
PLOT_KEYS = {"signals": list, "title": str}
DEVICE_KEYS = {
    "kind": str, "task": str, "io": str, "twin": str, "twin_args": dict, "limits": dict, "description": str,
}
"""Keys every ``[devices.NAME]`` table may hold; the rest are the kind's own settings."""
FOXGLOVE_KEYS = {"host": str, "port": int, "inputs": list, "description": str}
ROS_KEYS = {"domain_id": int, "publish": list, "subscribe": list}
ROS_TOPIC_KEYS = {
    "topic": str, "port": str, "source": str, "type": str, "qos": str, "joint_names": list, "every": int,
    "description": str, "range": list,
}
TASK_KEYS = {
    "runnable": str, "model": str, "args": dict, "period_ns": int, "priority": int,
    "cpu": int, "policy": str, "overrun": str, "description": str, "parameters": dict, "watchdog_periods": int,
    "max_consecutive_misses": int,
    "lock_blas_buffer": bool, "units": dict, "controllers": dict, "active": str, "blend_s": float,
}
CONTROLLER_KEYS = {"runnable": str, "model": str, "args": dict, "parameters": dict, "description": str}
PORT_KEYS = {
    "to": str, "source": str, "initial": list, "allow_nonfinite": bool, "capacity": int,
    "feed": str, "description": str, "range": list, "value_range": list, "nudge": str,
}
CONNECT_KEYS: dict[str, type] = {"from": str, "to": str}
CONNECT_OPTIONAL_KEYS: dict[str, type] = {"allow_nonfinite": bool,  # min, max, rate_per_s: numbers App.connect checks
                                          "min": object, "max": object, "rate_per_s": object}
RECORD_KEYS = {"signals": list}
TYPE_NAMES = {str: "a string", int: "an integer", float: "a number", dict: "a table", list: "an array",
              bool: "true or false"}


def _check_keys(path: str, where: str, table: dict[str, Any], allowed: Mapping[str, type]) -> None:
    for key, value in table.items():
        full = f"{where}.{clip(key, 40)}" if where else clip(key, 40)
        if key not in allowed:
            close = [k for k in allowed if _similar(k, key)]
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise AppFileError(path, full, f"unknown key{hint}; expected one of {sorted(allowed)}")
        expected = allowed[key]
        numeric = expected is float and isinstance(value, int)  # `blend_s = 1` is a number too
        if not (isinstance(value, expected) or numeric) or (expected in (int, float) and isinstance(value, bool)):
            raise AppFileError(path, full, f"expected {TYPE_NAMES[expected]}, got {shorten(value)}")


def _deeper_than(data: dict[str, Any], levels: int) -> str | None:
    """The top-level key under which tables and arrays nest more than ``levels`` deep, or None
    (walked with a stack, not by recursion: the point is not to recurse 5000 times)."""
    for key, value in data.items():
        stack = [(value, 1)]
        while stack:
            item, depth = stack.pop()
            if depth > levels:
                return key
            children = item.values() if isinstance(item, dict) else item if isinstance(item, list) else ()
            stack.extend((child, depth + 1) for child in children if isinstance(child, dict | list))
    return None


def _similar(a: str, b: str) -> bool:
    import difflib

    return difflib.SequenceMatcher(None, a[:40], b[:40]).ratio() >= 0.75


class CodeRefused(AppFileError):
    """The app's code (a module beside the app file, a model) is refused: who owns it or may write it."""


def load_app(path: str | Path) -> App:
    """Read and validate an app file; builds the runnables (in this process)."""
    with sources.collecting() as made_of:
        app = _load_app(path)
    app.sources = made_of
    return app


def _load_app(path: str | Path) -> App:
    file = Path(path)
    shown = clip(str(path), 200)
    try:
        if file.is_dir():
            raise AppFileError(shown, "", "is a directory; expected an app file (TOML)")
        with open(file, "rb") as stream:
            raw = stream.read(MAX_APP_FILE_BYTES + 1)
        if len(raw) > MAX_APP_FILE_BYTES:
            raise AppFileError(shown, "", f"larger than {MAX_APP_FILE_BYTES} bytes; not an app file")
        data = tomllib.loads(raw.decode("utf-8"))
    except FileNotFoundError:
        raise AppFileError(shown, "", "no such file") from None
    except OSError as error:
        raise AppFileError(shown, "", f"cannot read it: {error.strerror}") from None
    except UnicodeDecodeError as error:
        raise AppFileError(shown, "", f"not UTF-8 text (byte {error.start}); an app file is TOML") from None
    except tomllib.TOMLDecodeError as error:
        raise AppFileError(shown, "", f"not valid TOML: {clip(str(error), 160)}") from None
    except RecursionError:  # tomllib parses nested arrays and tables by recursion: 10 kB of [[[[ is enough
        raise AppFileError(shown, "", "not valid TOML: nested too deeply") from None
    deep = _deeper_than(data, MAX_NESTING_LEVELS)
    if deep is not None:  # code below (parameters, args, repr, pickle) walks tables by recursion too
        raise AppFileError(shown, clip(deep, 40), f"nested too deeply (more than "
                           f"{MAX_NESTING_LEVELS} levels of tables and arrays)")
    sources.note({str(file.resolve()): sources.digest_of_bytes(raw)})
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

    if not isinstance(data["tasks"], dict):
        raise AppFileError(shown, "tasks", "expected tables [tasks.NAME]")
    if len(data["tasks"]) > MAX_TASKS:  # before any runnable is built
        raise AppFileError(shown, "tasks", too_many_tasks(len(data["tasks"])))
    for task_name, table in data["tasks"].items():
        where = f"tasks.{clip(task_name, 40)}"
        if not isinstance(table, dict):
            raise AppFileError(shown, where, "expected a table [tasks.NAME]")
        _check_keys(shown, where, table, TASK_KEYS)
        runnable = _build_task_runnable(shown, where, table, base_dir)
        if "period_ns" not in table:
            raise AppFileError(shown, f"{where}.period_ns", "missing; e.g. period_ns = 1_000_000 for 1 kHz")
        try:
            app.add_task(
                task_name, runnable, period_ns=table["period_ns"],
                priority=table.get("priority", 80), cpu=table.get("cpu"),
                policy=table.get("policy", "fifo"), overrun=table.get("overrun", "skip"),
                watchdog_periods=table.get("watchdog_periods", DEFAULT_WATCHDOG_PERIODS),
                max_consecutive_misses=table.get("max_consecutive_misses"),
                lock_blas_buffer=table.get("lock_blas_buffer", False),
            )
            if "units" in table:
                app.set_units(task_name, table["units"])
        except AppError as error:
            raise AppFileError(shown, where, str(error)) from None

    _load_devices(shown, data.get("devices", {}), app, base_dir)

    for index, table in enumerate(data.get("connect", [])):
        where = f"connect[{index}]"
        if not isinstance(table, dict):
            raise AppFileError(shown, where, "expected a table [[connect]] with from and to")
        _check_keys(shown, where, table, CONNECT_KEYS | CONNECT_OPTIONAL_KEYS)
        for key in CONNECT_KEYS:
            if key not in table:
                raise AppFileError(shown, f"{where}.{key}", "missing")
        try:
            app.connect(parse_signal(table["from"], app, "from"), parse_signal(table["to"], app, "to"),
                        allow_nonfinite=table.get("allow_nonfinite", False), min=table.get("min"),
                        max=table.get("max"), rate_per_s=table.get("rate_per_s"))
        except AppError as error:
            raise AppFileError(shown, where, str(error)) from None

    for port_name, table in data.get("ports", {}).items():
        where = f"ports.{clip(port_name, 40)}"
        if not isinstance(table, dict):
            raise AppFileError(shown, where, "expected a table [ports.NAME]")
        _check_keys(shown, where, table, PORT_KEYS)
        if "range" in table and "value_range" in table:
            raise AppFileError(shown, f"{where}.value_range", "give range or value_range (the same), not both")
        try:
            app.port(
                port_name,
                to=parse_signal(table["to"], app, "to") if "to" in table else None,
                source=parse_signal(table["source"], app, "source") if "source" in table else None,
                initial=table.get("initial"),
                allow_nonfinite=table.get("allow_nonfinite", False),
                capacity=table.get("capacity", 4096),
                feed=(base_dir / table["feed"]) if "feed" in table else None,
                value_range=table.get("range", table.get("value_range")),
                nudge=table.get("nudge"),
            )
        except (AppError, TypeError, ValueError) as error:
            raise AppFileError(shown, where, str(error)) from None

    _load_ros(shown, data.get("ros", {}), app)
    if "foxglove" in data:
        _load_foxglove(shown, data["foxglove"], app)

    record = data.get("record", {})
    _check_keys(shown, "record", record, RECORD_KEYS)
    for index, text in enumerate(record.get("signals", [])):
        try:
            app.record(parse_signal(str(text), app, "signal"))
        except AppError as error:
            raise AppFileError(shown, f"record.signals[{index}]", str(error)) from None
    _load_plots(shown, data.get("plot", []), app)
    return app


def _load_plots(shown: str, plots: list[Any], app: App) -> None:
    """``[[plot]]``: ``signals = ["pi.setpoint_rad_s", "plant.speed_rad_s"]`` on one axis, ``title``."""
    for index, table in enumerate(plots):
        where = f"plot[{index}]"
        if not isinstance(table, dict):
            raise AppFileError(shown, where, "expected a table [[plot]] with signals = [...]")
        _check_keys(shown, where, table, PLOT_KEYS)
        signals = table.get("signals")
        if not signals or not all(isinstance(text, str) for text in signals):
            raise AppFileError(shown, f"{where}.signals", "expected signal names, e.g. ['pi.setpoint', 'motor.omega']")
        try:
            app.plot(*(parse_signal(text, app, "signal") for text in signals), title=table.get("title", ""))
        except AppError as error:
            raise AppFileError(shown, where, str(error)) from None


def _load_devices(shown: str, devices: dict[str, Any], app: App, base_dir: Path) -> None:
    """``[devices.NAME]``: kind, task, io, twin, limits, then the kind's own settings."""
    for name, table in devices.items():
        where = f"devices.{clip(name, 40)}"
        if not isinstance(table, dict):
            raise AppFileError(shown, where, "expected a table [devices.NAME]")
        common = {key: value for key, value in table.items() if key in DEVICE_KEYS}
        _check_keys(shown, where, common, DEVICE_KEYS)
        for key in ("kind", "task"):
            if key not in table:
                raise AppFileError(shown, f"{where}.{key}", "missing; a device needs kind and task")
        if "twin_args" in table and "twin" not in table:
            raise AppFileError(shown, f"{where}.twin_args", "given without twin")
        twin = None
        if "twin" in table:
            twin = _build_runnable(shown, where, {"runnable": table["twin"], "args": table.get("twin_args", {})},
                                   base_dir, key="twin")
        settings = {key: value for key, value in table.items() if key not in DEVICE_KEYS}
        try:
            if isinstance(table["kind"], str):  # else build_device says what is wrong with it
                settings = _paths_from(base_dir, device_class(table["kind"], name, shown), settings)
            device = build_device(table["kind"], name, settings, shown)
            app.add_device(name, device, task=table["task"], io=table.get("io", "let"), twin=twin,
                           limits=table.get("limits", {}))
        except DeviceError:
            raise
        except AppError as error:
            raise AppFileError(shown, where, str(error)) from None


def _paths_from(base_dir: Path, driver: Any, settings: dict[str, Any]) -> dict[str, Any]:
    """A device's relative paths (a serial port's link, say) taken from the app file's folder, as
    its feeds and modules are: the app runs the same from whichever folder it is started."""
    paths = {key for key, setting in getattr(driver, "settings", {}).items() if getattr(setting, "is_path", False)}
    return {key: _from_folder(base_dir, value) if key in paths and isinstance(value, str) and value and
            not value.startswith("/") and "://" not in value else value for key, value in settings.items()}


def _from_folder(base_dir: Path, relative: str) -> str:
    """``relative`` taken from ``base_dir`` (resolved: no link in it), its leading ``..`` climbed there, so
    the messages name ``…/runs/so100.tty``, not ``…/examples/so100_feetech/../../runs/so100.tty``. A ``..``
    after a name stays (that name may be a link)."""
    parts = Path(relative).parts
    ups = next((i for i, part in enumerate(parts) if part != ".."), len(parts))
    folder = base_dir
    for _ in range(ups):
        folder = folder.parent
    return str(folder.joinpath(*parts[ups:]))


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
            if direction == "publish" and "range" in table:
                raise AppFileError(shown, f"{where}.range", "range applies to [[ros.subscribe]] only")
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
                    app.ros_subscribe(table["topic"], port=table["port"], value_range=table.get("range"), **options)
            except AppError as error:
                raise AppFileError(shown, where, str(error)) from None


def _load_foxglove(shown: str, table: dict[str, Any], app: App) -> None:
    """``[foxglove]``: ``port`` (8765), ``host`` (127.0.0.1), ``inputs`` (input ports it may write)."""
    _check_keys(shown, "foxglove", table, FOXGLOVE_KEYS)
    inputs = table.get("inputs", [])
    if not all(isinstance(name, str) for name in inputs):
        raise AppFileError(shown, "foxglove.inputs", f"expected port names (strings), got {inputs!r}")
    try:
        app.serve_foxglove(table.get("port", 8765), host=table.get("host", "127.0.0.1"), inputs=inputs)
    except AppError as error:
        raise AppFileError(shown, "foxglove", str(error)) from None


def _build_task_runnable(shown: str, where: str, table: dict[str, Any], base_dir: Path) -> Runnable:
    """A task's runnable, or its ``[tasks.NAME.controllers]`` (several, one ``active``)."""
    if "controllers" not in table:
        for key in ("active", "blend_s"):
            if key in table:
                raise AppFileError(shown, f"{where}.{key}", "applies to a task with [tasks.NAME.controllers]")
        return _build_runnable(shown, where, table, base_dir)
    for key in ("runnable", "model", "args", "parameters"):
        if key in table:
            raise AppFileError(shown, f"{where}.{key}", "a task with controllers names its runnables in "
                               "[tasks.NAME.controllers.CONTROLLER], not here")
    if "active" not in table:
        raise AppFileError(shown, f"{where}.active", "missing: the controller that starts, e.g. active = \"pid\"")
    built: dict[str, Runnable] = {}
    for name, entry in table["controllers"].items():
        at = f"{where}.controllers.{clip(str(name), 40)}"
        entry_table = {"runnable": entry} if isinstance(entry, str) else entry
        if not isinstance(entry_table, dict):
            raise AppFileError(shown, at, 'expected "module:Class" or a table with runnable = "module:Class"')
        _check_keys(shown, at, entry_table, CONTROLLER_KEYS)
        built[str(name)] = _build_runnable(shown, at, entry_table, base_dir)
    try:
        return Controllers(built, table["active"], blend_s=table.get("blend_s", 0.5))
    except AppError as error:
        raise AppFileError(shown, where, str(error)) from None


def _build_runnable(shown: str, where: str, table: dict[str, Any], base_dir: Path, key: str = "runnable") -> Runnable:
    has_runnable, has_model = "runnable" in table, "model" in table
    if has_runnable == has_model:
        raise AppFileError(shown, where, 'give exactly one of runnable = "module:Class" or model = "kind:path"')
    args = table.get("args", {})
    parameters = _flat_parameters(table.get("parameters"))
    _check_finite_parameters(shown, where, parameters)
    if has_model:
        try:
            from rtloop.models import load_model, model_path
        except ImportError as error:
            raise AppFileError(shown, f"{where}.model", f"model support unavailable: {error}") from None
        path = model_path(table["model"], base_dir) if isinstance(table["model"], str) else None
        try:
            if path is not None:
                check_model_files(path)
        except ModuleRefused as error:
            raise CodeRefused(shown, f"{where}.model", str(error)) from None
        if parameters is not None:
            args = {**args, "parameters": parameters}
        try:
            return load_model(table["model"], base_dir, **args)
        except RtloopError as error:  # incl. a model that does not build: the compiler's own words, whole
            raise AppFileError(shown, f"{where}.model", str(error)) from error
        except (OSError, ValueError, TypeError) as error:
            raise AppFileError(shown, f"{where}.model", clip(str(error), 300)) from error
        except Exception as error:  # a model library or FMU failing in a way of its own
            raise AppFileError(shown, f"{where}.model", f"{type(error).__name__}: "
                               f"{clip(str(error), 200)}") from error
    target = table["runnable"]
    module_name, _, class_name = target.partition(":")
    args_key = f"{where}.{'args' if key == 'runnable' else key + '_args'}"
    key = f"{where}.{key}"
    if not _is_dotted_name(module_name) or not class_name.isidentifier():
        raise AppFileError(shown, key, f'{shorten(target)}: expected "module:Class"')
    module = _import_runnable_module(shown, key, module_name, base_dir)
    cls = getattr(module, class_name, None)
    if not isinstance(cls, type) or not issubclass(cls, Runnable):
        what = "has no" if cls is None else "has no Runnable subclass"
        raise AppFileError(shown, key, f"module {module_name!r} {what} {class_name!r}")
    try:
        runnable = cls(**args)
    except Exception as error:  # the constructor is user code: whatever it raises is a bad app
        raise AppFileError(shown, args_key, f"{clip(target)}({shorten(args, 60)}) failed: "
                           f"{type(error).__name__}: {clip(str(error), 120)}") from error
    if not isinstance(runnable, Runnable):
        raise AppFileError(shown, key, f"{target} is not a subclass of rtloop.Runnable")
    if parameters is not None:
        from rtloop.models.base import apply_parameters

        try:
            apply_parameters(runnable, parameters, target)
        except RtloopError as error:
            raise AppFileError(shown, f"{where}.parameters", str(error)) from None
    return runnable


def _flat_parameters(parameters: Any) -> Any:
    """``{ pan.r = 0.018 }`` is TOML for ``{"pan": {"r": 0.018}}``: back to ``{"pan.r": 0.018}``.

    So a 20-sim name with its backslash (``pan\\r``) is written with a dot, no escaping.
    """
    if not isinstance(parameters, dict):
        return parameters
    flat: dict[str, Any] = {}
    for name, value in parameters.items():
        if isinstance(value, dict):
            flat.update({f"{name}.{inner}": inner_value for inner, inner_value in _flat_parameters(value).items()})
        else:
            flat[name] = value
    return flat


def _check_finite_parameters(shown: str, where: str, parameters: Any) -> None:
    """TOML has ``nan`` and ``inf``: a parameter given one would reach a motor at cycle 0. Refused here,
    naming the key, as a port refuses them."""
    if not isinstance(parameters, dict):
        return
    for name, value in parameters.items():
        if isinstance(value, float) and not math.isfinite(value):
            raise AppFileError(shown, f"{where}.parameters.{name}", f"{value} is not a finite number")


def _is_dotted_name(text: str) -> bool:
    return bool(text) and all(part.isidentifier() for part in text.split("."))


def _import_runnable_module(shown: str, key: str, module_name: str, base_dir: Path) -> Any:
    """The named module: beside the app file (by path, only that file) or installed — never both."""
    beside = module_beside(base_dir, module_name)
    try:
        if beside is not None:
            installed = installed_origin(module_name)
            if installed is not None and Path(installed).resolve() != beside.resolve():
                raise AppFileError(shown, key, f"{beside} would shadow the installed module {module_name!r} "
                                   f"({clip(installed, 100)}); rename the file beside the app file")
            return load_module_file(module_name, beside.resolve())
        return importlib.import_module(module_name)
    except AppFileError:
        raise
    except ModuleRefused as error:
        raise CodeRefused(shown, key, str(error)) from None
    except ImportError as error:
        raise AppFileError(shown, key, f"cannot import module {module_name!r} (looked for {module_name}.py "
                           f"beside the app file, then installed modules): {clip(str(error), 120)}") from error
    except BaseException as error:  # SyntaxError, or anything the module raises while importing
        if isinstance(error, KeyboardInterrupt):
            raise
        raise AppFileError(shown, key, f"module {module_name!r} failed to import: {type(error).__name__}: "
                           f"{clip(str(error), 120)}") from error
