"""The package's layout: no import cycle, no private name used across modules.

Every module of ``rangeseg_cli`` is parsed (not imported) and every import
of another package module is read, at module level or inside a function
(the lazy imports that keep ``rangeseg --help`` fast are imports all the
same).
"""

from __future__ import annotations

import ast
from pathlib import Path

import rangeseg_cli

PACKAGE = Path(rangeseg_cli.__file__).parent
NAME = "rangeseg_cli"

#: Imports of a private name allowed across modules: (importing module, name).
PRIVATE_ALLOWED: set[tuple[str, str]] = set()


def _modules() -> dict[str, Path]:
    """Dotted names of the package's modules and packages (``__init__``) and their files."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


def _imports(module: str, path: Path, modules: dict[str, Path]
             ) -> list[tuple[str, str | None, int]]:
    """(imported module, name imported from it or None, line) of each package import."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: list[tuple[str, str | None, int]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(a.name, None, node.lineno) for a in node.names
                      if a.name.split(".")[0] == NAME]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                source = f"{base}.{node.module}" if node.module else base
            else:
                source = node.module or ""
            if source.split(".")[0] != NAME:
                continue
            for alias in node.names:
                submodule = f"{source}.{alias.name}"
                if submodule in modules:  # from . import x: the module x
                    found.append((submodule, None, node.lineno))
                else:
                    found.append((source, alias.name, node.lineno))
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {m: {target for target, _, _ in _imports(m, p, modules)
                if target in modules and target != m}
            for m, p in modules.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` (its modules, the first repeated at the end), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test_cycle_finder_finds_a_cycle_through_three_modules() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycle(graph) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_graph_reads_lazy_imports_inside_functions() -> None:
    graph = _graph()
    assert "rangeseg_cli.pipeline" in graph["rangeseg_cli"]  # __init__.__getattr__
    assert "rangeseg_cli.kernels.backend" in graph["rangeseg_cli.stages.edges"]


def test_no_module_of_the_package_imports_itself_through_others() -> None:
    cycle = _cycle(_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_no_private_name_is_imported_from_another_module() -> None:
    modules = _modules()
    found = []
    for module, path in modules.items():
        for target, name, line in _imports(module, path, modules):
            imported = name or target.rpartition(".")[2]
            private = imported.startswith("_") and not imported.startswith("__")
            if private and (module, imported) not in PRIVATE_ALLOWED:
                found.append(f"{path.name}:{line}: {imported} from {target}")
    assert not found, "private names imported across modules:\n" + "\n".join(found)
