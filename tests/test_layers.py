"""The import contract of the package layout (issue 14, "Folders that show the architecture").

Walks every module's imports with :mod:`ast` — no import is executed, so import order cannot
hide an arrow — and checks the arrows between the layers (docs/design.md):

- the pure core (``leafgate.gateway``) imports no shell, no transport and no file or socket I/O;
- the simulator never imports replay;
- there is no cycle between packages;
- loading the config imports no controller module (checked in a fresh interpreter);
- the ``leafgate`` command holds its stop signals before it imports anything but ``signal``
  (checked in a fresh interpreter).

Imports inside functions count too (a lazy import is still an arrow); those under
``if TYPE_CHECKING:`` do not (they exist only for the type checker).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections.abc import Iterator
from functools import cache
from pathlib import Path

import leafgate

PACKAGE = Path(leafgate.__file__).resolve().parent

CORE = "leafgate.gateway"
#: what the core must not reach, directly or through anything it imports
SHELL = (
    "leafgate.runtime",
    "leafgate.transport",
    "leafgate.record",
    "leafgate.replay",
    "leafgate.sim",
    "leafgate.can",
    "leafgate.settings",
    "leafgate.cli",
)
#: modules of I/O, threads and clocks the core's own modules must not import
IO_MODULES = frozenset(
    {
        "asyncio", "can", "csv", "io", "json", "logging", "mcap", "multiprocessing", "os",
        "pathlib", "select", "shutil", "socket", "sqlite3", "subprocess", "tempfile",
        "threading", "time", "yaml", "zenoh",
    }
)  # fmt: skip
#: the controller modules (algorithms) that loading a config must not import
CONTROLLERS = ("mpc", "baselines", "qp", "model", "reference")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


@cache
def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _type_checking_lines(tree: ast.Module) -> set[int]:
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for inner in node.body:
                lines.update(range(inner.lineno, (inner.end_lineno or inner.lineno) + 1))
    return lines


@cache
def imports_of(module: str) -> frozenset[str]:
    """Every module ``module`` imports (absolute names, ``from X import y`` as X and X.y)."""
    path = _modules()[module]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip = _type_checking_lines(tree)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if getattr(node, "lineno", None) in skip:
            continue
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            found.add(source)
            found.update(f"{source}.{alias.name}" for alias in node.names)
    return frozenset(found)


def internal_imports(module: str) -> frozenset[str]:
    """The leafgate modules ``module`` imports."""
    modules = _modules()
    return frozenset(m for m in imports_of(module) if m in modules and m != module)


def reachable(module: str) -> set[str]:
    """Every leafgate module ``module`` imports, directly or through others."""
    seen: set[str] = set()
    todo = [module]
    while todo:
        for dep in internal_imports(todo.pop()):
            if dep not in seen:
                seen.add(dep)
                todo.append(dep)
    return seen


def _in(module: str, packages: tuple[str, ...] | str) -> bool:
    packages = (packages,) if isinstance(packages, str) else packages
    return any(module == p or module.startswith(p + ".") for p in packages)


def package_of(module: str) -> str:
    """``leafgate.X`` for a module of a subpackage or a top-level module ``leafgate/X.py``."""
    return ".".join(module.split(".")[:2])


#: the entry point: it imports every command's package, and a package that runs command lines
#: (``batch`` runs the exact ``leafgate sim`` line of a case) may reach it; no arrow into it counts
ENTRY_POINT = "leafgate.cli"


def package_cycles() -> list[list[str]]:
    """The cycles of the package graph (one per strongly connected component)."""
    graph: dict[str, set[str]] = {}
    for module in _modules():
        if module == "leafgate":
            continue
        source = package_of(module)
        targets = {
            package_of(d) for d in internal_imports(module) if d not in ("leafgate", ENTRY_POINT)
        }
        graph.setdefault(source, set()).update(targets - {source})
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(node: str) -> None:  # Tarjan's strongly connected components
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return cycles


def _arrows(sources: Iterator[str], forbidden: tuple[str, ...]) -> list[str]:
    out = []
    for module in sources:
        for dep in sorted(reachable(module)):
            if _in(dep, forbidden):
                out.append(f"{module} reaches {dep}")
                break
    return out


def test_the_core_reaches_no_shell_no_transport() -> None:
    core = [m for m in _modules() if _in(m, CORE)]
    assert core, f"no core package {CORE}"
    bad = _arrows(iter(core), SHELL)
    assert not bad, "the pure core imports the shell: " + "; ".join(bad)


def test_the_core_imports_no_io_threads_or_clock() -> None:
    bad = [
        f"{module} imports {dep}"
        for module in _modules()
        if _in(module, CORE)
        for dep in sorted(imports_of(module))
        if dep.split(".")[0] in IO_MODULES
    ]
    assert not bad, "the pure core does I/O: " + "; ".join(bad)


def test_the_simulator_never_imports_replay() -> None:
    sim = (m for m in _modules() if _in(m, "leafgate.sim"))
    bad = _arrows(sim, ("leafgate.replay",))
    assert not bad, "; ".join(bad)


def test_no_package_cycle() -> None:
    cycles = package_cycles()
    assert not cycles, "packages in a cycle: " + " | ".join(" ↔ ".join(c) for c in cycles)


def test_the_config_modules_reach_no_controller() -> None:
    config = [m for m in _modules() if _in(m, ("leafgate.config", "leafgate.settings"))]
    forbidden = tuple(f"leafgate.control.{name}" for name in CONTROLLERS)
    bad = _arrows(iter(config), forbidden)
    assert not bad, "; ".join(bad)


def test_loading_the_config_imports_no_controller() -> None:
    """``import leafgate.settings`` in a fresh interpreter loads no algorithm module."""
    code = (
        "import sys, leafgate.settings\n"
        f"bad = sorted(m for m in sys.modules if m.rpartition('.')[2] in {CONTROLLERS!r}"
        " and m.startswith('leafgate.control.'))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "", f"loading the config imported {out.stdout.strip()}"


#: what ``leafgate.__main__`` may import before it holds SIGTERM and SIGHUP, beside ``signal``
#: and what ``signal`` itself needs (``enum``, ``functools`` …: already loaded by ``site`` in an
#: editable install, not in a plain one)
BEFORE_THE_HOLD = {
    "leafgate",
    "leafgate.runtime",
    "leafgate.runtime.hold",
    "leafgate.__main__",
    "__future__",
    "atexit",  # built into the interpreter (sys.builtin_module_names): nothing to load
}


def test_the_command_holds_its_stop_signals_before_any_heavy_import() -> None:
    """A SIGTERM before :func:`leafgate.runtime.hold.hold` is the default kill (status 143), so
    nothing costly may load before it: ``leafgate/__init__.py``, ``leafgate/runtime/__init__``
    and ``hold.py`` import ``signal`` only (``signals.py`` with logging and threads cost 12 ms;
    the interpreter's own start, some 14 ms, comes before any of it)."""
    code = (
        "import sys\n"
        "import signal\n"
        "before = set(sys.modules)\n"
        "import leafgate.__main__\n"
        "print(','.join(sorted(set(sys.modules) - before)))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    loaded = set(filter(None, out.stdout.strip().split(",")))
    assert "leafgate.runtime.hold" in loaded  # the check sees the imports it is about
    assert loaded <= BEFORE_THE_HOLD, (
        f"imported before the hold: {sorted(loaded - BEFORE_THE_HOLD)}"
    )


def test_the_contract_checker_sees_a_planted_arrow() -> None:
    """The walker is not vacuous: it finds arrows that exist (the shell imports the core)."""
    assert "leafgate.gateway.core" in reachable("leafgate.cli")
    assert any(_in(d, "leafgate.messages") for d in internal_imports("leafgate.gateway.core"))
