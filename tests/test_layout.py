"""The package's shape: no import cycle inside nrpose, no private name taken from another module.

Imports are read with ``ast`` from the sources (module level and inside
functions alike), relative imports resolved to modules. Importing ``a.b.c``
also runs the packages ``a.b`` and ``a`` first, so an edge goes to each
package on the way that is not already a package of the importer.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: package name -> source folder (pyproject's package-dir)
FOLDERS = {"nrpose": ROOT / "nrpose", "nrpose.rigs": ROOT / "rigs"}


def modules() -> dict[str, tuple[Path, bool]]:
    """Module name -> (source file, whether it is a package's __init__)."""
    found = {}
    for package, folder in FOLDERS.items():
        for path in sorted(folder.rglob("*.py")):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            is_package = parts[-1] == "__init__"
            if is_package:
                parts = parts[:-1]
            found[".".join([package] + parts)] = (path, is_package)
    return found


def imports(name: str, path: Path, is_package: bool, known) -> list[tuple[str, str | None, str, int]]:
    """(module, name taken from it or None, name bound, line) for every nrpose import of a module."""
    package = name if is_package else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(alias.name, None, alias.asname or alias.name.partition(".")[0], node.lineno)
                    for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            for alias in node.names:
                bound = alias.asname or alias.name
                if f"{target}.{alias.name}" in known:      # ``from package import module``
                    out.append((f"{target}.{alias.name}", None, bound, node.lineno))
                else:
                    out.append((target, alias.name, bound, node.lineno))
    return [r for r in out if r[0] == "nrpose" or r[0].startswith("nrpose.")]


def graph() -> dict[str, set[str]]:
    known = modules()
    edges = {name: set() for name in known}
    for name, (path, is_package) in known.items():
        own = {".".join(name.split(".")[:i]) for i in range(1, name.count(".") + 1 + is_package)}
        for target, _, _, _ in imports(name, path, is_package, known):
            parts = target.split(".")
            for i in range(1, len(parts) + 1):
                step = ".".join(parts[:i])
                if step in known and step not in own and step != name:
                    edges[name].add(step)
    return edges


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the graph as a list of modules (first == last), or None."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(edges[node]):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = "done"
        return None

    for node in sorted(edges):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test_the_sources_are_found():
    known = modules()
    assert {"nrpose.cli", "nrpose.io", "nrpose.model.character", "nrpose.pose.poser", "nrpose.rigs.humanoid"} <= set(known)
    edges = graph()
    assert "nrpose.model.character" in edges["nrpose.io.gltf_read"]
    assert "nrpose.io" in edges["nrpose.cli.info"]          # ``from ..io import load_character``
    assert "nrpose.io.files" in edges["nrpose.io.meshes"]    # relative import inside a package


def test_no_import_cycle():
    cycle = find_cycle(graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_the_cycle_finder_finds_cycles():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"b"}}) is None


def test_no_private_name_from_another_module():
    known = modules()
    taken = []
    for name, (path, is_package) in known.items():
        records = imports(name, path, is_package, known)
        taken += [f"{path.relative_to(ROOT)}:{line}: {n} from {target}" for target, n, _, line in records
                  if n is not None and n.startswith("_") and target != name]
        # ``module._name`` on a module bound by an import
        bound = {b for target, n, b, _ in records if n is None and target in known and target != "nrpose"}
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in bound
                    and node.attr.startswith("_") and not node.attr.startswith("__")):
                taken.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.value.id}.{node.attr}")
    assert not taken, "private names used across modules:\n" + "\n".join(taken)


def test_layers():
    """The data model reads no file and poses nothing; only the command line (and ``python -m nrpose``) imports the command line."""
    edges = graph()
    for name, targets in edges.items():
        if name.startswith("nrpose.model."):
            assert all(t in ("nrpose.errors", "nrpose.checks") or t.startswith("nrpose.model") for t in targets), \
                f"{name} imports {sorted(targets)}"
        if not name.startswith("nrpose.cli") and name != "nrpose.__main__":
            assert not any(t.startswith("nrpose.cli") for t in targets), f"{name} imports the CLI"
