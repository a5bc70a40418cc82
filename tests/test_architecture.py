"""The package's layers: imports point one way, and no module imports itself back round.

Every ``import`` in ``src/rtloop`` counts, wherever it stands (a function-level import that
hides a cycle is still a cycle). Importing ``rtloop.a.b`` also runs ``rtloop/a/__init__.py``,
so it counts as an import of ``rtloop.a`` too (except from inside ``rtloop.a``, whose
``__init__`` has run already; importing a name from it still counts). Only the root ``rtloop/__init__.py`` (the
public facade, the top of the stack) is exempt, and no module of the package may import it
for a name: modules import from where a name is defined.
"""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "rtloop"

# Which layers each layer may import (besides itself). The floor imports only the floor.
FLOOR = "floor"
ALLOWED: dict[str, set[str]] = {
    FLOOR: set(),
    "linux": {FLOOR},
    "stats": {FLOOR},
    "ros.types": set(),
    "ipc": {FLOOR, "linux"},
    "models": {FLOOR},
    "io": {FLOOR, "linux"},
    "app": {FLOOR, "models", "ros.types", "io"},
    "ros": {FLOOR, "linux", "ros.types", "app", "ipc"},
    "record": {FLOOR, "stats", "app", "ipc", "ros", "ros.types"},
    "runtime": {FLOOR, "linux", "stats", "app", "io", "ipc", "models", "record", "ros", "ros.types"},
    "report": {FLOOR, "stats", "record"},
    "toolbox": {FLOOR, "linux", "stats", "app", "io", "ipc", "models", "record", "ros", "ros.types", "runtime",
                "report"},
    "cli": {FLOOR, "linux", "stats", "app", "io", "ipc", "models", "record", "ros", "ros.types", "runtime",
            "report", "toolbox", "cli"},
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def all_modules() -> dict[str, Path]:
    return {module_name(path): path for path in PACKAGE.rglob("*.py")}


def layer_of(module: str) -> str:
    parts = module.split(".")
    if module in ("rtloop.ros", "rtloop.ros.types"):  # the package's __init__ runs first: it imports nothing
        return "ros.types"
    if module in ("rtloop", "rtloop.__main__"):
        return "facade"
    return parts[1] if parts[1] in ALLOWED else FLOOR


def imports_of(module: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The rtloop modules ``module`` imports, at any depth of its code, with their parent packages."""
    is_package = path.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base if is_package else base[:-1]
                base = base[: len(base) - node.level + 1]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            submodules = [f"{stem}.{alias.name}" for alias in node.names if f"{stem}.{alias.name}" in modules]
            names_only_submodules = len(submodules) == len(node.names)
            targets = submodules if names_only_submodules else [stem, *submodules]
        for target in targets:
            if target != "rtloop" and not target.startswith("rtloop."):
                continue
            if target in modules:
                found.add(target)
            parts = target.split(".")
            for depth in range(2, len(parts)):  # each package above the target, but not the root
                package = ".".join(parts[:depth])
                if package in modules and not module.startswith(package + "."):  # own packages run first anyway
                    found.add(package)
    found.discard(module)
    return found


@functools.cache  # the sources do not change during a run; each of the ~130 tests below used to parse them all
def import_graph() -> dict[str, set[str]]:
    modules = all_modules()
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's algorithm, iterative; components of more than one module are cycles."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in graph:
                    continue
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                components.append(sorted(component))
    return [component for component in components if len(component) > 1]


def test_no_import_cycles() -> None:
    graph = {name: deps - {"rtloop"} for name, deps in import_graph().items() if name != "rtloop"}
    assert strongly_connected(graph) == []


def test_the_cycle_finder_finds_cycles() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert strongly_connected(graph) == [["a", "b", "c"]]


def test_relative_and_function_level_imports_count(tmp_path: Path) -> None:
    source = "def f():\n    from ..ipc import segments\n    import rtloop.app.builder\n"
    path = tmp_path / "x.py"
    path.write_text(source)
    modules = {"rtloop.ipc": Path(), "rtloop.ipc.segments": Path(), "rtloop.app": Path(),
               "rtloop.app.builder": Path(), "rtloop.runtime.x": path}
    assert imports_of("rtloop.runtime.x", path, modules) == {
        "rtloop.ipc", "rtloop.ipc.segments", "rtloop.app", "rtloop.app.builder"}


@pytest.mark.parametrize("module", sorted(m for m in all_modules() if m not in ("rtloop", "rtloop.__main__")))
def test_imports_point_down(module: str) -> None:
    graph = import_graph()
    layer = layer_of(module)
    allowed = ALLOWED[layer] | {layer}
    wrong = sorted(dep for dep in graph[module] if layer_of(dep) not in allowed)
    assert not wrong, f"{module} ({layer}) imports {wrong}; {layer} may import only {sorted(allowed)}"


def test_the_description_knows_nothing_of_running() -> None:
    graph = import_graph()
    for module in (m for m in graph if layer_of(m) == "app"):
        assert not {dep for dep in graph[module] if layer_of(dep) in ("runtime", "ipc", "record", "cli")}, module


def test_the_description_builds_no_runtime_objects() -> None:
    """app/ describes devices; how a task's process runs them (``io.host``) and the twins that stand
    in for them in a simulation (``io.twin``) are the engine's, made by ``runtime/layout.py``."""
    graph = import_graph()
    for module in (m for m in graph if layer_of(m) == "app"):
        assert not graph[module] & {"rtloop.io.host", "rtloop.io.twin"}, module


def test_the_engine_imports_none_of_the_tools_built_on_it() -> None:
    graph = import_graph()
    for module in (m for m in graph if layer_of(m) in ("runtime", "linux")):
        assert not {dep for dep in graph[module] if dep.startswith("rtloop.toolbox")}, module


MAX_MODULE_LINES = 600
BEING_SPLIT: dict[str, str] = {}
"""Modules over the bound that work in progress is taking under it (each reason says which). Remove an
entry when its module is under the bound (not enforced here: the work that shrinks it lands on its own)."""


def test_no_module_is_over_600_lines() -> None:
    """Small readable modules: a module over 600 lines is two modules. C files and generated files
    are exempt (``_schema.h`` is generated; each C file follows a Python reference held to the bound)."""
    long = {str(path.relative_to(SRC)): n for path in PACKAGE.rglob("*.py")
            if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES}
    assert {name: n for name, n in long.items() if name not in BEING_SPLIT} == {}


SUPERVISOR_MAX_LINES = 450
SUPERVISOR_SIDE = ("rtloop.runtime.supervisor", "rtloop.runtime.session", "rtloop.runtime.task_watch",
                   "rtloop.runtime.task_messages", "rtloop.runtime.run_view")
"""The modules of the ``rtloop run`` process around the task processes (docs/architecture.md §1)."""


def test_the_supervisor_keeps_only_the_processes_lifecycle() -> None:
    """runtime/supervisor.py starts, watches and stops the task processes, and no more: what the tasks
    say through their pipes is read by runtime/task_messages.py, what a person watching the run sees
    (progress, notices, the Foxglove live view) is runtime/run_view.py's, the summary is built by
    runtime/run_summary.py. A module that takes one of those jobs back grows past this bound."""
    source = (PACKAGE / "runtime" / "supervisor.py").read_text()
    assert len(source.splitlines()) <= SUPERVISOR_MAX_LINES
    assert ".recv(" not in source, "the task pipes are read in runtime/task_messages.py"
    assert "rtloop.record.foxglove_live" not in import_graph()["rtloop.runtime.supervisor"], "runtime/run_view.py"


def test_the_task_process_imports_nothing_of_the_supervisor_side() -> None:
    """A task process (runtime/task.py and all it imports, at any depth) loads neither the supervisor's
    modules nor the recorder's: each would cost the real-time process memory it locks and never uses."""
    graph, seen, todo = import_graph(), set(), ["rtloop.runtime.task"]
    while todo:
        for dep in graph[todo.pop()] - seen:
            seen.add(dep)
            todo.append(dep)
    wrong = sorted(m for m in seen if m in SUPERVISOR_SIDE or m == "rtloop.record" or m.startswith("rtloop.record."))
    assert not wrong, f"runtime/task.py imports {wrong} (directly or through what it imports)"


def test_the_task_process_imports_everything_before_its_loop() -> None:
    """runtime/task.py imports at its top only: an import inside one of its functions could run
    inside the real-time loop (a file read, the import lock) the first time the loop calls it.
    What it imports lazily on purpose would have to be imported before the loop starts instead."""
    tree = ast.parse((PACKAGE / "runtime" / "task.py").read_text())
    inside = [f"line {node.lineno}: {ast.unparse(node)}" for function in ast.walk(tree)
              if isinstance(function, ast.FunctionDef | ast.AsyncFunctionDef)
              for node in ast.walk(function) if isinstance(node, ast.Import | ast.ImportFrom)]
    assert inside == []


def test_every_type_ignore_names_its_code_and_reason() -> None:
    """mypy runs strict (pyproject.toml); an exception to it says which check and why, on its line
    (here, so that landing checks it: tests/test_tooling.py holds the rest of the tooling's rules)."""
    bare = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            if "type: ignore" in line and not re.search(r"# type: ignore\[[a-z-]+(,[a-z-]+)*\]  # \S", line):
                bare.append(f"{path.relative_to(SRC)}:{number}")
    assert not bare, f"type: ignore without [code] and '  # reason' after it: {bare}"


# --- repeats removed from the tests and the benchmarks (#29's review): kept from coming back ---------

TESTS = Path(__file__).resolve().parent
BENCHMARKS = TESTS.parent / "benchmarks"
OWN_TAILS_YET = {"bench_latency.py", "bench_wakeup_trace.py"}
"""Benchmarks that still write their own options, Targets and Machine sections: they take
``_common.py``'s helpers when next changed (remove them here then)."""


class _Shape(ast.NodeTransformer):
    """A function with every name, attribute and argument renamed and its docstring dropped: what
    stays is its shape, so a copy with other names is the same."""

    def visit_FunctionDef(self, node: ast.FunctionDef) -> ast.AST:
        if node.body and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant):
            node.body = node.body[1:]
        node.name = "_"
        return self.generic_visit(node)

    def visit_Name(self, node: ast.Name) -> ast.AST:
        return ast.Name("_", node.ctx)

    def visit_Attribute(self, node: ast.Attribute) -> ast.AST:
        node.attr = "_"
        return self.generic_visit(node)

    def visit_arg(self, node: ast.arg) -> ast.AST:
        node.arg = "_"
        return self.generic_visit(node)


def _methods(path: Path, name: str) -> dict[str, str]:
    """``name`` method of every class in ``path``: class name → its shape."""
    found = {}
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ClassDef):
            for item in node.body:
                if isinstance(item, ast.FunctionDef) and item.name == name:
                    found[node.name] = ast.dump(_Shape().visit(item))
    return found


def _code_strings(path: Path) -> set[str]:
    """The string constants of a module's code (its docstrings left out: prose may name anything)."""
    tree = ast.parse(path.read_text(), str(path))
    docstrings = {id(body[0].value) for node in ast.walk(tree)
                  if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef)
                  and (body := node.body) and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)}
    return {node.value for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings}


def test_the_line_that_answers_at_once_is_written_once() -> None:
    """A servo line handing back the same answers to every sync read is tests/servo_lines.py's, for the
    tests and benchmarks/bench_servos.py alike; it was written twice, under two names."""
    shared = TESTS / "servo_lines.py"
    reference = _methods(shared, "receive")["AnswersAtOnce"]
    modules = sorted([*TESTS.glob("*.py"), *BENCHMARKS.rglob("*.py")])
    copies = [f"{path.relative_to(TESTS.parent)}:{cls}" for path in modules
              if path != shared for cls, shape in _methods(path, "receive").items() if shape == reference]
    assert copies == [], "use servo_lines.AnswersAtOnce (or servos_answering_at_once)"


@pytest.mark.parametrize("path", sorted(p for p in BENCHMARKS.glob("bench_*.py") if p.name not in OWN_TAILS_YET),
                         ids=lambda path: path.name)
def test_a_benchmark_ends_through_the_shared_helpers(path: Path) -> None:
    """The "### Targets" and "### Machine" sections, ``--quick`` and the hold on /dev/cpu_dma_latency are
    benchmarks/_common.py's (``closing_sections``, ``add_output_options``, ``PmQos``), so every benchmark
    prints them alike; the hop processes' start is bench_channels.run_hop_processes."""
    strings = _code_strings(path)
    assert not strings & {"### Machine", "### Targets", "**MISSED**"}, "use _common.closing_sections"
    assert "--quick" not in strings, "use _common.add_output_options and parse_options"
    assert "/dev/cpu_dma_latency" not in strings, "use _common.PmQos (rtloop's own rt.CpuDmaLatency)"
    if path.name != "bench_channels.py":
        assert "a hop benchmark process died while starting" not in strings, "use bench_channels.run_hop_processes"


def test_the_hold_on_cpu_dma_latency_is_written_once() -> None:
    """linux/rt.py's CpuDmaLatency holds /dev/cpu_dma_latency, for the supervisor and the benchmarks
    (``_common.PmQos``); the doctor looks at the file under its own root."""
    holders = sorted(str(path.relative_to(SRC.parent)) for path in [*PACKAGE.rglob("*.py"), *BENCHMARKS.rglob("*.py")]
                     if "/dev/cpu_dma_latency" in _code_strings(path))
    assert holders == ["src/rtloop/linux/rt.py"], "use rt.CpuDmaLatency (benchmarks: _common.PmQos)"


def test_the_byte_layout_twins_and_the_busy_wait_are_written_once() -> None:
    """A layout compiled and as the Python reference is conftest.layout_twins; a runnable spinning to a
    deadline calls rt_test_runnables.busy_until."""
    twins = []
    for path in sorted(TESTS.glob("*.py")):
        source = path.read_text()
        for node in ast.walk(ast.parse(source, str(path))):
            if isinstance(node, ast.FunctionDef) and path.name != "conftest.py":
                body = ast.get_source_segment(source, node) or ""
                if 'setenv("RTLOOP_PURE_PYTHON"' in body and body.count("ByteLayout(") >= 2:
                    twins.append(f"{path.name}:{node.name}")
    assert twins == [], "use conftest.layout_twins"
    spins = (TESTS / "rt_test_runnables.py").read_text().count("while time.monotonic_ns() <")
    assert spins == 1
