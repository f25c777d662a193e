"""The architecture's rules, read from the source with `ast` (nothing is imported):
scenes -> acoustic_sim -> shards -> learn flows one way, no module imports itself back through
others (function-level imports count too: they are circles that only wait to be called),
kernels depend on Warp alone, and modules stay small enough to read."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("scenes", "acoustic_sim", "learn")
MAX_LINES = 450


def modules(root: Path = ROOT) -> dict[str, Path]:
    """Dotted name -> file, for every module of our packages (a package is its __init__)."""
    found = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def imports(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """Every module `name` imports, at any depth of the file: ours resolved to dotted names (a
    `from X import y` names X.y when that is a module), others by their top-level name."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            found |= {f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names}
    return found


def graph(root: Path = ROOT) -> dict[str, set[str]]:
    known = modules(root)
    return {name: {m for m in imports(name, path, known) if m in known} - {name} for name, path in known.items()}


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Import circles: strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def test_no_import_circles():
    assert cycles(graph()) == []


def test_cycle_finder_finds_a_circle_through_a_function_level_import(tmp_path):
    """The check itself: config -> air at the top, air -> config inside a function."""
    (tmp_path / "acoustic_sim").mkdir()
    for package in PACKAGES:
        (tmp_path / package).mkdir(exist_ok=True)
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "acoustic_sim" / "config.py").write_text("from .air import chirp\n")
    (tmp_path / "acoustic_sim" / "air.py").write_text("def chirp():\n    from .config import X\n")
    assert cycles(graph(tmp_path)) == [["acoustic_sim.air", "acoustic_sim.config"]]


def test_learn_reads_shards_and_never_imports_the_simulator():
    for name, path in modules().items():
        if name.startswith("learn"):
            tops = {m.split(".")[0] for m in imports(name, path, modules())}
            assert not tops & {"warp", "acoustic_sim", "scenes"}, (name, tops)


def test_kernels_depend_on_warp_alone():
    stdlib = set(sys.stdlib_module_names)
    for name, path in modules().items():
        if name.startswith("acoustic_sim.kernels"):
            others = {m for m in imports(name, path, modules()) if m.split(".")[0] not in stdlib | {"warp"}}
            others -= {m for m in others if m.startswith("acoustic_sim.kernels")}  # one kernel file may use another
            assert not others, (name, others)


def test_modules_stay_readable():
    for path in modules().values():
        key = str(path.relative_to(ROOT))
        lines = len(path.read_text().splitlines())
        assert lines <= MAX_LINES, f"{key} has {lines} lines (> {MAX_LINES}): split it by stage"
