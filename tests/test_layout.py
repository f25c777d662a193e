"""The architecture's rules, read from the source with `ast` (nothing is imported):
scenes -> acoustic_sim -> shards -> learn flows one way (both command lines on the settings
grammar in clitools, which needs the standard library alone), no module imports itself back
through others (function-level imports count too: they are circles that only wait to be called), the
simulator's three stages (engine, datasets, formats) sit on its configuration and import each
other one way only, kernels depend on Warp alone, and modules stay small enough to read."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("clitools", "scenes", "acoustic_sim", "learn")
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


def test_simulator_and_scenes_never_import_torch():
    """torch is the `[learn]` extra: simulating, generating and beamforming work without it."""
    for name, path in modules().items():
        if not name.startswith("learn"):
            assert "torch" not in {m.split(".")[0] for m in imports(name, path, modules())}, name


def test_the_settings_grammar_needs_the_standard_library_alone():
    """clitools, the `--set` grammar of both command lines, imports neither of them (nor numpy):
    the learner may use it without the simulator."""
    stdlib = set(sys.stdlib_module_names)
    for name, path in modules().items():
        if name.split(".")[0] == "clitools":
            others = {m for m in imports(name, path, modules()) if m.split(".")[0] not in stdlib | {"clitools"}}
            assert not others, (name, others)


def test_kernels_depend_on_warp_alone():
    stdlib = set(sys.stdlib_module_names)
    for name, path in modules().items():
        if name.startswith(KERNELS):
            others = {m for m in imports(name, path, modules()) if m.split(".")[0] not in stdlib | {"warp"}}
            others -= {m for m in others if m.startswith(KERNELS)}  # one kernel file may use another
            assert not others, (name, others)


KERNELS = "acoustic_sim.engine.kernels"
# What each part of the simulator may import of the simulator (besides itself and the package's
# public names in acoustic_sim/__init__.py, which only re-export the engine and configuration).
# The base is the configuration and what it is built from (air, array), devices and small helpers.
BASE = ("config", "config_checks", "air", "array", "settings", "devices", "extras", "user_warning")
MAY_IMPORT = {
    "base": {"base"},
    "engine": {"base", "engine"},
    "render": {"base", "engine"},  # pictures of every stage's output
    "datasets": {"base", "engine", "render", "datasets"},
    "formats": {"base", "engine", "render", "datasets", "formats"},
    # the engine run backwards on recordings, read from our datasets or other formats (CHIRP)
    "calibrate": {"base", "engine", "datasets", "formats", "calibrate"},
    "cli": {"base", "engine", "render", "datasets", "formats", "calibrate", "cli"},
}


def part(module: str) -> str | None:
    """The part of acoustic_sim that a module belongs to (None for the package itself)."""
    names = module.split(".")
    if names[0] != "acoustic_sim" or len(names) == 1:
        return None
    if names[1] in BASE:
        return "base"
    if names[1] in ("__main__", "cli", "cli_text", "cli_scene", "cli_calibrate"):
        return "cli"
    return names[1]


def layer_breaches(edges: dict[str, set[str]]) -> list[tuple[str, str]]:
    """(importer, imported) pairs that break MAY_IMPORT, or that reach into the kernels from
    outside the engine."""
    found = []
    for name, targets in sorted(edges.items()):
        mine = part(name)
        if mine is None:
            continue
        for target in sorted(targets):
            theirs = part(target)
            if theirs is None:
                continue
            if theirs not in MAY_IMPORT[mine] or (target.startswith(KERNELS) and mine != "engine"):
                found.append((name, target))
    return found


def test_every_simulator_module_belongs_to_a_part():
    assert set(MAY_IMPORT) >= {part(name) for name in modules() if name.startswith("acoustic_sim.")}


def test_stages_import_one_way():
    """The engine imports neither datasets nor formats, datasets no formats, nothing the CLI, and
    only the engine reaches into the kernels."""
    assert layer_breaches(graph()) == []


def test_layer_check_finds_a_breach():
    """The check itself: the engine importing the dataset pipeline, a format reaching into a kernel."""
    edges = {
        "acoustic_sim.engine.sonar": {"acoustic_sim.datasets.suites", "acoustic_sim.config"},
        "acoustic_sim.formats.chirp": {"acoustic_sim.engine.kernels.signals", "acoustic_sim.engine.beamform"},
        "acoustic_sim.datasets.plan": {"acoustic_sim.datasets.shards"},
    }
    assert layer_breaches(edges) == [
        ("acoustic_sim.engine.sonar", "acoustic_sim.datasets.suites"),
        ("acoustic_sim.formats.chirp", "acoustic_sim.engine.kernels.signals"),
    ]


def test_modules_stay_readable():
    for path in modules().values():
        key = str(path.relative_to(ROOT))
        lines = len(path.read_text().splitlines())
        assert lines <= MAX_LINES, f"{key} has {lines} lines (> {MAX_LINES}): split it by stage"
