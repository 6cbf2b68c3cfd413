"""The import graph of mkf_ros/ (read from the sources): no cycle between modules, and the
layers import downwards only (``core/`` nothing above it, nothing below imports the compile
orchestration :mod:`mkf_ros.kernels`).

Every ``import`` statement counts, at module level or inside a function (a lazy import is
still a dependency: it only moves when it is paid). The parent packages Python imports
implicitly are not edges; an explicit ``import mkf_ros`` is one (to ``mkf_ros/__init__.py``)."""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "mkf_ros"


def _module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(root: Path = PKG) -> dict[str, set[str]]:
    """Module -> the mkf_ros modules it imports (``from a.b import c`` imports ``a.b.c`` when
    that is a module, else ``a.b``; relative imports resolved)."""
    modules = {_module_name(p, root): p for p in root.rglob("*.py")}
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*up, base] if base else up)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                           for a in node.names]
            graph[name] |= {t for t in targets if t in modules and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
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
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_finder_sees_a_cycle_through_a_function_level_import(tmp_path: Path) -> None:
    """The check itself: a two-module cycle closed by an import inside a function, and one
    through a relative import, are found; a chain is not a cycle."""
    pkg = tmp_path / "mkf_ros"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from mkf_ros import b\n")
    (pkg / "b.py").write_text("def f():\n    from mkf_ros.a import g\n")
    (pkg / "sub" / "c.py").write_text("from . import d\n")
    (pkg / "sub" / "d.py").write_text("from .c import x\n")
    (pkg / "e.py").write_text("import mkf_ros.a\n")
    found = cycles(import_graph(pkg))
    assert sorted(found) == [["mkf_ros.a", "mkf_ros.b"], ["mkf_ros.sub.c", "mkf_ros.sub.d"]]


def test_no_import_cycle_in_the_package() -> None:
    graph = import_graph()
    assert len(graph) > 50 and graph["mkf_ros.core.filter"]  # the sources were read
    assert cycles(graph) == []


def test_core_imports_nothing_above_it() -> None:
    """``core/`` (the filters: NumPy and numba) imports only ``core/`` and the version."""
    graph = import_graph()
    above = {m: sorted(t for t in deps if not t.startswith("mkf_ros.core")
                       and t != "mkf_ros._version")
             for m, deps in graph.items() if m.startswith("mkf_ros.core")}
    assert {m: d for m, d in above.items() if d} == {}


def test_only_front_ends_import_the_compile_orchestration() -> None:
    """:mod:`mkf_ros.kernels` decides what is compiled and when; the filters, the simulator
    and the streaming rules it compiles never import it."""
    graph = import_graph()
    users = sorted(m for m, deps in graph.items() if "mkf_ros.kernels" in deps)
    low = ("mkf_ros.core", "mkf_ros.sim", "mkf_ros.stream", "mkf_ros.api")
    assert users and not [m for m in users if m.startswith(low)]
