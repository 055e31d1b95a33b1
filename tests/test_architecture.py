"""The house rules (STYLE.md, "The house as it stands"), checked on the source with `ast`.

Layers, top to bottom: uavmm -> benchmarks -> sim -> agent | fusion_server -> transport -> shared. An import only
points down (or inside its own package); no two modules import each other, directly or around a loop;
a module stays readable in one sitting (at most MAX_LINES lines) and opens with a docstring.
Every import counts: module level, inside functions and under `if TYPE_CHECKING:` alike.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Package -> layer; a module may import its own package and the packages of lower layers.
LAYERS = {"uavmm": 6, "benchmarks": 5, "sim": 4, "agent": 3, "fusion_server": 3, "transport": 2, "shared": 1}
MAX_LINES = 600

# Known violations, allowed while they are being removed (issue 20 removed the last ones). Each entry
# must still be a violation: when you fix one, delete it here (the test says so). Adding one needs a
# reason in its comment and a plan to remove it.
#: Imports that point up or sideways, as "importer -> imported".
KNOWN_LAYER_BREAKS: set[str] = set()
#: Import cycles (strongly connected groups of modules), exactly as they stand.
KNOWN_CYCLES: set[frozenset[str]] = set()
#: Modules over MAX_LINES lines.
KNOWN_LARGE: set[str] = set()


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def modules() -> dict[str, Path]:
    """Every module of the packages (tests excluded): dotted name -> file."""
    return {_module_name(p): p for pkg in LAYERS for p in sorted((ROOT / pkg).rglob("*.py"))}


def _imported_names(name: str, path: Path, known: dict[str, Path]) -> Iterator[str]:
    """Dotted names the module's import statements refer to (absolute and relative imports)."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - (node.level - 1)]
                target = ".".join([*base, *([node.module] if node.module else [])])
            else:
                target = node.module or ""
            for alias in node.names:
                # `from pkg import module` imports the module; `from module import name`, the module
                sub = f"{target}.{alias.name}"
                yield sub if sub in known else target


@cache
def import_graph() -> dict[str, frozenset[str]]:
    """Module -> the modules of the packages it imports (resolved to the longest known module)."""
    mods = modules()
    graph = {}
    for name, path in mods.items():
        targets = set()
        for imported in _imported_names(name, path, mods):
            parts = imported.split(".")
            while parts and ".".join(parts) not in mods:
                parts.pop()
            if parts and ".".join(parts) != name:
                targets.add(".".join(parts))
        graph[name] = frozenset(targets)
    return graph


def import_cycles(graph: dict[str, frozenset[str]]) -> set[frozenset[str]]:
    """Strongly connected groups of two or more modules (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: set[frozenset[str]] = set()
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[v] = min(low[v], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                group = set()
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    group.add(w)
                    if w == v:
                        break
                if len(group) > 1:
                    found.add(frozenset(group))
    return found


def test_the_cycle_finder_finds_loops_and_only_loops() -> None:
    graph = {"a": frozenset({"b"}), "b": frozenset({"c"}), "c": frozenset({"a"}), "d": frozenset({"a"}),
             "e": frozenset({"f"}), "f": frozenset({"e"}), "g": frozenset()}
    assert import_cycles(graph) == {frozenset({"a", "b", "c"}), frozenset({"e", "f"})}


def layer_breaks(graph: dict[str, frozenset[str]]) -> set[str]:
    """Imports of a package in the same or a higher layer, as "importer -> imported"."""
    bad = set()
    for name, targets in graph.items():
        pkg = name.split(".")[0]
        for target in targets:
            other = target.split(".")[0]
            if other != pkg and LAYERS[other] >= LAYERS[pkg]:
                bad.add(f"{name} -> {target}")
    return bad


def test_the_layer_check_refuses_up_and_sideways_imports() -> None:
    graph = {"agent.a": frozenset({"shared.x", "sim.y", "fusion_server.z"}), "sim.y": frozenset({"agent.a"}),
             "shared.x": frozenset({"agent.a"}), "uavmm.c": frozenset({"benchmarks.b"})}
    assert layer_breaks(graph) == {"agent.a -> sim.y", "agent.a -> fusion_server.z", "shared.x -> agent.a"}


def test_imports_point_down_the_layers() -> None:
    breaks = layer_breaks(import_graph())
    new = sorted(breaks - KNOWN_LAYER_BREAKS)
    assert not new, ("imports that do not point down uavmm -> benchmarks -> sim -> agent | fusion_server -> "
                     "shared (move what is needed down, or pass it in from above):\n  " + "\n  ".join(new))
    fixed = sorted(KNOWN_LAYER_BREAKS - breaks)
    assert not fixed, f"no longer layer breaks, remove them from KNOWN_LAYER_BREAKS: {fixed}"


def test_no_import_cycles() -> None:
    cycles = import_cycles(dict(import_graph()))
    new = sorted(sorted(c) for c in cycles - KNOWN_CYCLES)
    assert not new, ("modules that import each other (directly or around a loop): one concept split wrong, "
                     "or a third concept hiding between them:\n  " + "\n  ".join(" <-> ".join(c) for c in new))
    fixed = sorted(sorted(c) for c in KNOWN_CYCLES - cycles)
    assert not fixed, f"no longer cycles, remove them from KNOWN_CYCLES: {fixed}"


def test_modules_stay_readable_in_one_sitting() -> None:
    sizes = {name: len(path.read_text(encoding="utf-8").splitlines()) for name, path in modules().items()}
    large = {name for name, n in sizes.items() if n > MAX_LINES}
    new = sorted(large - KNOWN_LARGE)
    assert not new, (f"modules over {MAX_LINES} lines (make a package whose modules name the steps): "
                     + ", ".join(f"{n} ({sizes[n]})" for n in new))
    fixed = sorted(KNOWN_LARGE - large)
    assert not fixed, f"no longer over {MAX_LINES} lines, remove them from KNOWN_LARGE: {fixed}"


@pytest.mark.parametrize("name", sorted(modules()))
def test_every_module_opens_with_a_docstring(name: str) -> None:
    tree = ast.parse(modules()[name].read_text(encoding="utf-8"))
    assert ast.get_docstring(tree), f"{name} should open with a docstring saying what it is for"
