"""The project's five packages import each other without cycles.

The graph is built from the source (ast), not by importing: every `import X` / `from X import Y`
anywhere in a module is an edge, at the top level, inside functions (deferred imports) and in
`if TYPE_CHECKING:` blocks alike, so a cycle hidden behind a function-level or type-only import
counts too. Only imports of the project's own modules are edges; `from pkg import name` points to
the submodule `pkg.name` when there is one, else to `pkg` itself. Relative imports are resolved.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("mvgeo", "splat", "denoise", "eval", "data_synth")


def project_modules(root: Path = ROOT) -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is_package) for every .py file of the five packages."""
    modules = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            is_package = parts[-1] == "__init__"
            if is_package:
                parts = parts[:-1]
            modules[".".join(parts)] = (path, is_package)
    return modules


def _resolve(name: str, modules: dict) -> str | None:
    """The longest prefix of `name` that is a project module (None outside the project)."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def import_graph(modules: dict[str, tuple[Path, bool]]) -> dict[str, set[str]]:
    """Module -> the project modules it imports anywhere in its source."""
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, (path, is_package) in modules.items():
        package = name if is_package else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    parts = parts[:len(parts) - (node.level - 1)]
                    base = ".".join([*parts, base] if base else parts)
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    targets.append(sub if sub in modules else base)
            for target in targets:
                resolved = _resolve(target, modules)
                if resolved is not None and resolved != name:
                    graph[name].add(resolved)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0

    def visit(v: str) -> None:  # recursion depth <= number of modules (a few hundred)
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def test_cycle_finder_finds_a_known_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_graph_sees_function_level_relative_and_type_checking_imports(tmp_path):
    pkg = tmp_path / "mvgeo"
    (pkg / "sub").mkdir(parents=True)
    for d in (pkg, pkg / "sub"):
        (d / "__init__.py").write_text("")
    (pkg / "sub" / "a.py").write_text("def f():\n    from mvgeo.sub import b\n")
    (pkg / "sub" / "b.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .a import f\n")
    (pkg / "c.py").write_text("from .sub.a import f\nimport numpy\n")
    graph = import_graph({k: v for k, v in project_modules(tmp_path).items() if k.startswith("mvgeo")})
    assert graph["mvgeo.sub.a"] == {"mvgeo.sub.b"}
    assert graph["mvgeo.sub.b"] == {"mvgeo.sub.a"}
    assert graph["mvgeo.c"] == {"mvgeo.sub.a"}
    assert cycles(graph) == [["mvgeo.sub.a", "mvgeo.sub.b"]]


def test_the_project_has_no_import_cycles():
    modules = project_modules()
    assert len(modules) > 100  # the five packages were found
    found = cycles(import_graph(modules))
    assert found == [], "import cycles:\n" + "\n".join(" <-> ".join(c) for c in found)
