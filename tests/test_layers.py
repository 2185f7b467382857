"""The house has one-way floors (docs/design.md §1, issue 49): every import of a gmjax module — at the
top of a file or inside a function — goes to a lower floor or stays on its own, and no set of modules
imports itself in a circle."""

from __future__ import annotations

import ast
from pathlib import Path

GMJAX = Path(__file__).resolve().parents[1] / "gmjax"

#: Floors, bottom to top: a module may import its own floor and those below. The key is the first part
#: of the module's name under gmjax (a package or a module); "gmjax" is the package's __init__.
FLOORS = [
    {"_types", "_jitcache", "_loops", "_progress", "_pytree", "_plotting", "_version"},
    {"gaussian", "inputs"},
    {"mixture", "quadrature"},
    {"_validate", "metrics", "split"},
    {"reduction", "models", "params"},
    {"filters", "pcrb"},
    {"multitarget", "montecarlo", "scenarios"},
    {"fitting", "tune", "studies", "_default_study"},
    {"gmjax", "cli"},
]
FLOOR = {name: level for level, names in enumerate(FLOORS) for name in names}


def _modules() -> dict[str, Path]:
    mods = {}
    for path in GMJAX.rglob("*.py"):
        name = ".".join(path.relative_to(GMJAX.parent).with_suffix("").parts)
        mods[name.removesuffix(".__init__")] = path
    return mods


def _imports(mods: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the gmjax modules it imports (``from gmjax.x import y`` counts ``gmjax.x.y`` when that
    is a module, else ``gmjax.x``)."""

    def resolve(name: str) -> str:
        while name not in mods and "." in name:
            name = name.rsplit(".", 1)[0]
        return name if name in mods else ""

    edges: dict[str, set[str]] = {m: set() for m in mods}
    for m, path in mods.items():
        for node in ast.walk(ast.parse(path.read_text())):
            targets = []
            if (
                isinstance(node, ast.ImportFrom)
                and node.level == 0
                and (node.module or "").startswith("gmjax")
            ):
                targets = [
                    f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in mods else resolve(node.module)
                    for a in node.names
                ]
            elif isinstance(node, ast.Import):
                targets = [resolve(a.name) for a in node.names if a.name.startswith("gmjax")]
            edges[m] |= {t for t in targets if t and t != m}
    return edges


def _floor_key(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "gmjax"


def test_every_module_has_a_floor():
    missing = sorted({_floor_key(m) for m in _modules()} - set(FLOOR))
    assert not missing, f"put these in FLOORS (and docs/design.md): {missing}"


def test_imports_go_down_or_stay_on_their_floor():
    mods = _modules()
    upward = sorted(
        f"{m} -> {t}"
        for m, targets in _imports(mods).items()
        for t in targets
        if FLOOR[_floor_key(t)] > FLOOR[_floor_key(m)]
    )
    assert not upward, "imports that run up a floor:\n" + "\n".join(upward)


def test_models_do_not_import_filters():
    mods = _modules()
    bad = sorted(
        f"{m} -> {t}"
        for m, targets in _imports(mods).items()
        if m.startswith("gmjax.models")
        for t in targets
        if t.startswith("gmjax.filters")
    )
    assert not bad, bad


def test_no_circle_of_modules():
    """Tarjan's strongly connected components of the module graph (package __init__ files, which only
    re-export their submodules' names, are left out as targets): none has more than one module."""
    mods = _modules()
    packages = {m for m, p in mods.items() if p.name == "__init__.py"}
    graph = {
        m: sorted(t for t in ts if t not in packages) for m, ts in _imports(mods).items() if m not in packages
    }
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
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
                circles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    assert not circles, circles


def test_the_floors_see_a_planted_upward_import(tmp_path, monkeypatch):
    """The checks are live: a models file that imports the filters is caught by both."""
    fake = {"gmjax.models.base": tmp_path / "base.py", "gmjax.filters.base": tmp_path / "fbase.py"}
    fake["gmjax.models.base"].write_text("def f():\n    from gmjax.filters.base import StepInputs\n")
    fake["gmjax.filters.base"].write_text("from gmjax.models.base import f\n")
    edges = _imports(fake)
    assert edges["gmjax.models.base"] == {"gmjax.filters.base"}
    assert FLOOR[_floor_key("gmjax.filters.base")] > FLOOR[_floor_key("gmjax.models.base")]
