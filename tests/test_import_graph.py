"""The first-party import graph (issue 13): no cycle, and no first-party import inside a function
unless a start-up cost justifies it (``LAZY``, each with its reason).

Every ``import`` statement of ``companion/`` and ``simvehicle/`` counts, at module level, inside
functions and under ``if TYPE_CHECKING`` alike: a cycle hidden by an import inside a function is
still a cycle. ``from companion.x import y`` is an edge to ``companion.x.y`` when that is a
module, else to ``companion.x``; importing a submodule also runs its package's ``__init__``, which
is not counted as an edge (a package importing its own submodules is not a cycle).
Lazy imports of third-party libraries (matplotlib, scipy, pyarrow, dask, pymavlink) are fine.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("companion", "simvehicle")

#: (module, function) -> why the first-party import inside it is lazy. Each is a start-up cost
#: the command would pay for nothing; none dodges a cycle (the graph below has none either way).
LAZY: dict[tuple[str, str], str] = {
    ("companion.cli", "_dispatch"): "each subcommand loads only its own code: diagnose scipy, fleet dask, "
                                    "run pymavlink's link; --help and usage errors load none of it",
    ("simvehicle.cli", "_dispatch"): "serve loads the link and sockets, sweep numba and dask: each only for itself",
    ("simvehicle.cli", "_scenario"): "simvehicle.tools.plots loads matplotlib, only for --plot",
    ("companion.tools.replay", "run_cli"): "companion.tools.plot loads matplotlib, only for --plot "
                                           "(tests/test_lazy_imports.py)",
    ("companion.diagnose.closed_loop.command", "_sensor_mode"): "the sensor-only diagnosis loads scipy.signal and "
                                                                "scipy.stats (about 0.3 s), which the closed-loop "
                                                                "diagnosis does without (issue 12's time budget)",
    ("companion.recordings.load", "load_recording"): "each reader only for its format: the .tlog reader loads "
                                                     "pymavlink's dialect and the native kernels (about 40 ms), the "
                                                     "importers about 30 ms more; replay and info are measured "
                                                     "against the read (issue 17)",
}


@dataclass(frozen=True)
class Import:
    source: str  # the importing module
    target: str  # the first-party module imported
    line: int
    function: str | None  # the enclosing function, None at module or class level


def module_files() -> dict[str, Path]:
    mods: dict[str, Path] = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = path
    return mods


def _owner(name: str, mods: dict[str, Path]) -> str | None:
    while name and name not in mods:
        name = name.rpartition(".")[0]
    return name or None


def _targets(node: ast.Import | ast.ImportFrom, module: str, mods: dict[str, Path]) -> list[str]:
    if isinstance(node, ast.Import):
        return [t for a in node.names if (t := _owner(a.name, mods))]
    base = node.module or ""
    if node.level:
        pkg = module if mods[module].name == "__init__.py" else module.rpartition(".")[0]
        for _ in range(node.level - 1):
            pkg = pkg.rpartition(".")[0]
        base = f"{pkg}.{base}" if base else pkg
    out = []
    for a in node.names:
        sub = f"{base}.{a.name}"
        t = sub if sub in mods else _owner(base, mods)
        if t:
            out.append(t)
    return out


def imports(mods: dict[str, Path]) -> list[Import]:
    found: list[Import] = []

    def visit(node: ast.AST, module: str, function: str | None) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                visit(child, module, function or child.name)
                continue
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                found.extend(Import(module, t, child.lineno, function)
                             for t in _targets(child, module, mods) if t != module)
            visit(child, module, function)

    for module, path in mods.items():
        visit(ast.parse(path.read_text(encoding="utf-8"), str(path)), module, None)
    return found


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in edges.get(v, ()):
                out.append(sorted(comp))

    for v in sorted(set(edges) | {w for ws in edges.values() for w in ws}):
        if v not in index:
            strong(v)
    return sorted(out)


def _where(imps: list[Import], comp: list[str]) -> str:
    inside = set(comp)
    return "; ".join(f"{i.source}:{i.line} -> {i.target}" + (f" (in {i.function})" if i.function else "")
                     for i in imps if i.source in inside and i.target in inside)


@pytest.fixture(scope="module")
def graph() -> tuple[dict[str, Path], list[Import]]:
    mods = module_files()
    return mods, imports(mods)


def test_cycle_finder_finds_a_cycle_and_only_cycles():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": {"c"}, "d": {"a", "c"}}) == []
    assert cycles({"a": {"a"}}) == [["a"]]


def test_the_graph_sees_module_and_function_level_imports(graph):
    mods, imps = graph
    assert {"companion.recordings.load", "companion.recordings.columnar", "companion.recordings.importers.ulog",
            "simvehicle.server.server"} <= set(mods)
    pairs = {(i.source, i.target, i.function) for i in imps}
    assert ("companion.recordings.importers.ulog", "companion.recordings.importers.common", None) in pairs
    assert ("companion.recordings.load", "companion.recordings.tlog_reader", "load_recording") in pairs


def test_no_import_cycle(graph):
    _, imps = graph
    edges: dict[str, set[str]] = {}
    for i in imps:
        edges.setdefault(i.source, set()).add(i.target)
    found = cycles(edges)
    assert not found, "import cycles: " + " | ".join(_where(imps, c) for c in found)


def test_first_party_imports_inside_functions_are_justified(graph):
    _, imps = graph
    lazy = sorted({(i.source, i.function, i.target, i.line) for i in imps if i.function is not None})
    unjustified = [f"{s}:{line} imports {t} inside {f}()" for s, f, t, line in lazy if (s, f) not in LAZY]
    assert not unjustified, ("first-party imports inside functions (import at module level, or add to LAZY "
                             "with the start-up cost that justifies it): " + "; ".join(unjustified))


def test_every_lazy_entry_is_still_used(graph):
    _, imps = graph
    used = {(i.source, i.function) for i in imps if i.function is not None}
    assert set(LAZY) <= used, f"stale LAZY entries: {sorted(set(LAZY) - used)}"


#: the layers of docs/layout.md, lowest first: a module may import its own layer and those below,
#: never one above (``companion`` and ``simvehicle`` themselves hold only a docstring). Every
#: first-party module belongs to exactly one layer (``test_every_module_has_one_layer``).
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base", ("companion", "companion.errors", "companion.progress", "companion.config", "companion.mavlink_ids",
              "companion.rotation", "companion.native", "simvehicle")),
    ("the step", ("companion.step",)),
    ("recordings", ("companion.recordings",)),
    ("the MAVLink side", ("companion.mavlink",)),
    ("tools over recordings", ("companion.tools",)),
    ("analysis", ("companion.diagnose",)),
    ("fleet", ("companion.fleet",)),
    ("the simulated vehicle's models", ("simvehicle.model",)),
    ("the simulator's engines", ("simvehicle.engines",)),
    ("the simulator's server", ("simvehicle.server",)),
    ("the simulator's tools", ("simvehicle.tools",)),
    ("entry points", ("companion.cli", "companion.__main__", "companion.ardupilot_script", "simvehicle.cli",
                      "simvehicle.__main__")),
    ("old paths, one-line re-exports to remove in the next release",
     ("companion.replay", "companion.recording", "simvehicle.sim")),
)

#: (importer, imported) -> why this import from a lower layer into a higher one is allowed
UPWARD: dict[tuple[str, str], str] = {
    ("companion.step.profiles", "companion.recordings.load"): "detect_profile reads a Recording's messages (the "
                                                             "form's type, no reader)",
    ("companion.step.profiles", "companion.recordings.importers.common"): "GRAVITY_M_S2, the one value of g the "
                                                                         "accelerometer units are built from",
}


def layer_of(module: str) -> int | None:
    """The index in ``LAYERS`` of the longest prefix that names ``module`` or one of its packages."""
    best: tuple[int, int] | None = None
    for k, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and (best is None or len(p) > best[0]):
                best = (len(p), k)
    return None if best is None else best[1]


def upward(imps: list[Import]) -> list[str]:
    """Every import (module level or inside a function) from a lower layer into a higher one that
    ``UPWARD`` does not justify."""
    out = []
    for i in imps:
        src, tgt = layer_of(i.source), layer_of(i.target)
        if src is not None and tgt is not None and tgt > src and (i.source, i.target) not in UPWARD:
            out.append(f"{i.source}:{i.line} ({LAYERS[src][0]}) imports {i.target} ({LAYERS[tgt][0]})")
    return out


def test_the_layer_check_fails_an_import_into_a_higher_layer():
    down = Import("companion.tools.replay", "companion.step.core", 1, None)
    up = Import("companion.step.core", "companion.tools.replay", 2, None)
    lazy_up = Import("companion.recordings.load", "companion.diagnose.report", 3, "load_recording")
    assert upward([down]) == []
    assert upward([up]) == ["companion.step.core:2 (the step) imports companion.tools.replay (tools over recordings)"]
    assert len(upward([lazy_up])) == 1  # inside a function too
    assert layer_of("companion.diagnose.sensor.band") == layer_of("companion.diagnose.report")
    assert layer_of("companion.replay") != layer_of("companion.tools.replay")  # the longest prefix decides


def test_every_module_has_one_layer(graph):
    mods, _ = graph
    assert [m for m in mods if layer_of(m) is None] == []


def test_no_import_from_a_lower_layer_into_a_higher_one(graph):
    _, imps = graph
    found = upward(imps)
    assert not found, "imports into a higher layer (docs/layout.md): " + "; ".join(found)


def test_every_upward_exception_is_still_used(graph):
    _, imps = graph
    used = {(i.source, i.target) for i in imps}
    assert set(UPWARD) <= used, f"stale UPWARD entries: {sorted(set(UPWARD) - used)}"


def test_every_package_init_imports_nothing(graph):
    """Importing one module never loads a sibling it does not use: each ``__init__.py`` holds a
    docstring and no import (``from __future__`` aside)."""
    mods, _ = graph
    for module, path in mods.items():
        if path.name == "__init__.py":
            tree = ast.parse(path.read_text(encoding="utf-8"))
            imported = [n for n in ast.walk(tree) if isinstance(n, ast.Import | ast.ImportFrom)
                        and not (isinstance(n, ast.ImportFrom) and n.module == "__future__")]
            assert not imported, module
