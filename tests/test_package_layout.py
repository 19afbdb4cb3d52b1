"""The package's shape, read from its source (AST, nothing imported): no module imports another
package's private name, and no modules import each other in a circle.

- Private: a name or module starting with one underscore may be imported only within the package
  that holds it (`morphgs.metrics._arrays` by `morphgs.metrics.*`). What another package needs is
  made public where it lives. The binding `morphgs._core` is the exception: it is the whole
  distribution's private extension module (as pydantic's `pydantic_core._pydantic_core`).
- Circles: every import, at module level or inside a function, is an edge from the importing
  module to the module it names; the graph has no cycle. The root package `morphgs` (the API
  facade that re-exports the others) is not a node: `import morphgs` inside a function uses the
  public API.
"""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "python" / "morphgs"
BINDING = "morphgs._core"


def _modules() -> dict[str, tuple[Path, bool]]:
    """{dotted name: (file, is a package)}."""
    out = {}
    for p in sorted(PKG.rglob("*.py")):
        parts = list(p.relative_to(PKG.parent).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_pkg else parts)] = (p, is_pkg)
    return out


def _imports(mods: dict[str, tuple[Path, bool]]) -> list[tuple[str, str, str | None, int]]:
    """(importer, module named, imported name or None, line) of every morphgs import."""
    out = []
    for name, (path, is_pkg) in mods.items():
        package = name if is_pkg else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    src = ".".join(base + ([node.module] if node.module else []))
                else:
                    src = node.module or ""
                if src == "morphgs" or src.startswith("morphgs."):
                    out += [(name, src, a.name, node.lineno) for a in node.names]
            elif isinstance(node, ast.Import):
                out += [(name, a.name, None, node.lineno) for a in node.names
                        if a.name == "morphgs" or a.name.startswith("morphgs.")]
    return out


def _package(name: str, mods: dict[str, tuple[Path, bool]]) -> str:
    return name if mods.get(name, (None, False))[1] else name.rpartition(".")[0]


def test_no_module_imports_another_packages_private_name() -> None:
    mods = _modules()
    bad = []
    for importer, src, name, line in _imports(mods):
        home = _package(importer, mods)
        dotted = f"{src}.{name}" if name else src
        parts = dotted.split(".")
        for i, part in enumerate(parts):
            if not part.startswith("_") or part.startswith("__"):
                continue
            private = ".".join(parts[: i + 1])
            if private == BINDING or private.startswith(BINDING + "."):
                break
            # a private module belongs to the package holding it; a private name to its module's package
            owner = ".".join(parts[:i]) if private in mods else _package(".".join(parts[:i]), mods)
            if owner != home:
                bad.append(f"{importer} (line {line}) imports {private}, private to {owner}")
            break
    assert not bad, "\n".join(bad)


def test_no_import_circle() -> None:
    mods = _modules()
    edges: dict[str, set[str]] = {m: set() for m in mods}
    for importer, src, name, _ in _imports(mods):
        target = f"{src}.{name}" if name and f"{src}.{name}" in mods else src
        if target in mods and target not in (importer, "morphgs"):
            edges[importer].add(target)
    # Tarjan's strongly connected components, iteratively
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    cycles = []
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(edges[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    x = stack.pop()
                    on.discard(x)
                    comp.append(x)
                    if x == v:
                        break
                if len(comp) > 1:
                    cycles.append(sorted(comp))
    assert not cycles, "import circles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_the_checks_see_what_they_look_for(tmp_path: Path) -> None:
    # the private check resolves relative imports and private modules the way the tests above rely on
    mods = _modules()
    assert "morphgs.metrics._arrays" in mods and mods["morphgs.ablation.stages"][1]
    found = {(i, s, n) for i, s, n, _ in _imports(mods)}
    assert ("morphgs.metrics.image", "morphgs.metrics", "_arrays") in found
    assert ("morphgs.evaluation.core", "morphgs.evaluation", "report") in found  # a lazy import counts
