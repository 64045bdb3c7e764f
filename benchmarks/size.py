"""The size of the package and of its refinement, and the keys of ``rangeseg config``.

Issue 33's targets: the package at most 16,000 lines, the refinement's code at
most half of its 4,925 lines of 2026-11-27, at most 50 configuration keys, no
import cycle. Prints the figures and writes ``benchmarks/results/size.json``.
Beside all lines it counts the lines of code (not blank, comment or docstring):
at the issue's filing (commit 8c71907) the package had 9,473 of its 18,054
lines of code and the refinement 2,253 of its 4,825.

Usage::

    .venv/bin/python benchmarks/size.py
"""

from __future__ import annotations

import ast
import json
from pathlib import Path

from rangeseg_cli.config import key_reference

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "rangeseg_cli"
OUT = ROOT / "benchmarks" / "results" / "size.json"

#: The modules of the steps beyond the paper (the refinement and the noise it scales by).
REFINEMENT = ("refinement", "split", "recut", "recover", "facets", "chamfer", "refine",
              "carve", "merge", "fill", "occlusion", "noise", "regions")


def module_name(path: Path) -> str:
    """Dotted name of a module of the package, relative to it (``batch``, ``refine.cut``)."""
    rel = path.relative_to(PACKAGE).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def imports_of(path: Path) -> set[str]:
    """The package modules ``path`` imports (module level or inside functions)."""
    here = module_name(path).split(".")
    package = here if path.name == "__init__.py" else here[:-1]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            base = package[:len(package) - node.level + 1]
            target = ".".join([*base, *(node.module or "").split(".")]).strip(".")
            if node.module:
                out.add(target)
            else:  # from . import x: x may be a module
                out.update(n for n in (f"{target}.{a.name}".strip(".") for a in node.names)
                           if _exists(n))
    return out


def _exists(name: str) -> bool:
    stem = PACKAGE.joinpath(*name.split("."))
    return stem.with_suffix(".py").exists() or (stem / "__init__.py").exists()


def code_lines(text: str) -> int:
    """Lines of ``text`` (a module) that are code: not blank, comment or docstring."""
    doc: set[int] = set()
    for node in ast.walk(ast.parse(text)):
        owner = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)
        first = node.body[0] if isinstance(node, owner) and node.body else None
        if (isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
                and isinstance(first.value.value, str)):
            doc.update(range(first.lineno, (first.end_lineno or first.lineno) + 1))
    return sum(1 for i, line in enumerate(text.splitlines(), start=1)
               if i not in doc and line.strip() and not line.strip().startswith("#"))


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles of ``graph`` (one path per strongly connected component)."""
    found, state = [], {}

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                found.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, [*stack, nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    return found


def main() -> None:
    files = sorted(PACKAGE.rglob("*.py"))
    texts = {module_name(p): p.read_text(encoding="utf-8") for p in files}
    lines = {m: len(t.splitlines()) for m, t in texts.items()}
    code = {m: code_lines(t) for m, t in texts.items()}

    def in_refinement(m: str) -> bool:
        return m.split(".")[-1] in REFINEMENT or m.startswith("refine.")

    refinement = sum(n for m, n in lines.items() if in_refinement(m))
    graph = {module_name(p): imports_of(p) for p in files}
    result = {"package_lines": sum(lines.values()), "refinement_lines": refinement,
              "package_code_lines": sum(code.values()),
              "refinement_code_lines": sum(n for m, n in code.items() if in_refinement(m)),
              "config_keys": len(key_reference()), "import_cycles": cycles(graph),
              "largest_modules": sorted(lines.items(), key=lambda kv: -kv[1])[:8]}
    print(f"package: {result['package_lines']} lines (target <= 16000)")
    print(f"refinement: {refinement} lines (target <= 2462, half of 4925)")
    print(f"of which code (not blank, comment or docstring): package "
          f"{result['package_code_lines']}, refinement {result['refinement_code_lines']}")
    print(f"rangeseg config: {result['config_keys']} keys (target <= 50)")
    print(f"import cycles: {result['import_cycles'] or 'none'}")
    OUT.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
