"""The import contract: layers go one way and no module imports itself back through others; and
the house rule that no module of rg_core or rg_ros grows past MAX_LINES (split it by capability).

Every import counts, also those inside functions (a lazy import is still a dependency); a registry
names its backends as "package.module:attr" strings, which are not imports. Read with ast, so a
test failure names the arrow that breaks the contract.
"""
from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MAX_LINES = 400

# Lower layers first; a package imports only packages of lower layers.
LAYERS = [
    {"rg_core.util", "rg_core.config", "rg_core.geometry", "rg_core.batch"},
    {"rg_core.render", "rg_core.io"},
    {"rg_core.synth", "rg_core.viz", "rg_core.perception"},
    {"rg_core.models", "rg_core.field"},
    {"rg_core.map"},
    {"rg_core.grounding"},
    {"rg_core.eval"},
    {"rg_core.report"},
    {"rg_core.cli", "rg_ros"},
]


def modules() -> dict[str, Path]:
    out = {}
    for pkg in ("rg_core", "rg_ros"):
        for p in (REPO / pkg).rglob("*.py"):
            parts = p.relative_to(REPO).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = p
    return out


def import_edges(mods: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the project modules it imports (anywhere in its body)."""
    edges: dict[str, set[str]] = {}
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text())):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module != "__future__":
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join(up + ([node.module] if node.module else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            for t in targets:
                while t and t not in mods:
                    t = t.rpartition(".")[0]
                if t and t != name:
                    edges.setdefault(name, set()).add(t)
    return edges


def package(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2]) if parts[0] == "rg_core" and len(parts) > 1 else parts[0]


def layer_of(pkg: str) -> int:
    for i, layer in enumerate(LAYERS):
        if pkg in layer:
            return i
    raise AssertionError(f"package {pkg} is in no layer of tests/test_layers.py: place it")


def upward(edges: dict[str, set[str]]) -> list[str]:
    """The imports from a package to one of its own or a higher layer."""
    out = []
    for a, targets in edges.items():
        for b in targets:
            pa, pb = package(a), package(b)
            if pa != pb and "rg_core" not in (pa, pb) and layer_of(pa) <= layer_of(pb):
                out.append(f"{a} -> {b}")
    return sorted(out)


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in list(edges):
        if v not in index:
            visit(v)
    return found


def test_every_arrow_points_down():
    bad = upward(import_edges(modules()))
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def test_no_import_cycles():
    found = cycles(import_edges(modules()))
    assert not found, f"import cycles: {found}"


def test_the_contract_can_fail(tmp_path):
    """A lazy import inside a function, two levels up, closing a cycle and pointing up a layer."""
    (tmp_path / "rg_core" / "map").mkdir(parents=True)
    (tmp_path / "rg_core" / "eval").mkdir()
    store, metric = tmp_path / "rg_core" / "map" / "store.py", tmp_path / "rg_core" / "eval" / "metric.py"
    store.write_text("def f():\n    from ..eval.metric import g\n    return g\n")
    metric.write_text("from rg_core.map.store import f\n")
    edges = import_edges({"rg_core.map.store": store, "rg_core.eval.metric": metric})
    assert edges == {"rg_core.map.store": {"rg_core.eval.metric"}, "rg_core.eval.metric": {"rg_core.map.store"}}
    assert upward(edges) == ["rg_core.map.store -> rg_core.eval.metric"]
    assert cycles(edges) == [["rg_core.eval.metric", "rg_core.map.store"]]


def too_long(mods: dict[str, Path], limit: int = MAX_LINES) -> list[str]:
    """'path: N lines' for every module longer than `limit` lines."""
    out = []
    for p in sorted(mods.values()):
        n = len(p.read_text(encoding="utf-8").splitlines())
        if n > limit:
            out.append(f"{p.relative_to(REPO) if p.is_relative_to(REPO) else p}: {n} lines")
    return out


def test_no_module_over_the_line_limit(tmp_path):
    long = too_long(modules())
    assert not long, f"over {MAX_LINES} lines (split by capability, one public home each): {long}"
    f = tmp_path / "big.py"   # the check itself can fail
    f.write_text("x = 1\n" * (MAX_LINES + 1))
    assert too_long({"big": f}) == [f"{f}: {MAX_LINES + 1} lines"]
