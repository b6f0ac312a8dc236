"""The layout's limits in fbspost/ (docs/architecture.md): what is too long, what shares state
through parent classes, and what imports in a cycle.

Run from the repository root:  python bench/sizes.py [--graph]
Prints one line per offender; nothing when the layout is clean (exit status 0, else 1):
- a module over 600 lines, a class over 250, a function over 80 (from ``def`` / ``class`` to the
  last line of the body, nested ones too);
- a class with more than one parent class of the project, and a parent class of the project that
  reads ``self.X`` it never sets or defines (a mixin: its state is another class's);
- an import cycle between modules (every import, those inside functions and under
  TYPE_CHECKING too), and between packages;
- a private name (``_name``) imported from another module: what a module gives is public.
``--graph`` also prints each package and the packages it imports, lowest first.
"""
from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from pathlib import Path

MODULE_LINES = 600
LIMITS = {ast.ClassDef: 250, ast.FunctionDef: 80, ast.AsyncFunctionDef: 80}
ROOT = Path(__file__).resolve().parents[1]


def modules(package: Path) -> dict[str, ast.Module]:
    """Dotted name -> parsed source of every module under ``package`` (a package by its name)."""
    found = {}
    for path in sorted(package.rglob("*.py")):
        parts = path.relative_to(package.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        found[name] = ast.parse(path.read_text())
    return found


def too_long(trees: dict[str, ast.Module]) -> Iterator[str]:
    for name, tree in trees.items():
        lines = tree.body[-1].end_lineno if tree.body else 0
        if lines > MODULE_LINES:
            yield f"module {name} {lines} lines"
        for node in ast.walk(tree):
            limit = LIMITS.get(type(node))
            if limit is not None and node.end_lineno - node.lineno + 1 > limit:
                yield f"{'class' if isinstance(node, ast.ClassDef) else 'function'} {name}.{node.name} " \
                      f"{node.end_lineno - node.lineno + 1} lines"


def _defined(cls: ast.ClassDef) -> set[str]:
    """What ``cls`` itself owns: its methods and class attributes, and what it assigns to self."""
    owned = set()
    for node in ast.walk(cls):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node in cls.body:
            owned.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)) and node in cls.body:
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            owned.update(t.id for t in targets if isinstance(t, ast.Name))
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) \
                and isinstance(node.value, ast.Name) and node.value.id == "self":
            owned.add(node.attr)
    return owned


def _read(cls: ast.ClassDef) -> set[str]:
    return {node.attr for node in ast.walk(cls) if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load)
            and isinstance(node.value, ast.Name) and node.value.id == "self"}


def mixins(trees: dict[str, ast.Module]) -> Iterator[str]:
    classes = {node.name: (module, node) for module, tree in trees.items()
               for node in ast.walk(tree) if isinstance(node, ast.ClassDef)}

    def project_bases(cls: ast.ClassDef) -> list[str]:
        names = (base.id if isinstance(base, ast.Name) else getattr(base, "attr", "") for base in cls.bases)
        return [name for name in names if name in classes]

    def owned(name: str) -> set[str]:
        cls = classes[name][1]
        return _defined(cls).union(*(owned(base) for base in project_bases(cls)))

    parents = set()
    for name, (module, cls) in classes.items():
        bases = project_bases(cls)
        parents.update(bases)
        if len(bases) > 1:
            yield f"class {module}.{name} has {len(bases)} parent classes of the project: {', '.join(bases)}"
    for name in sorted(parents):
        module, cls = classes[name]
        foreign = sorted(_read(cls) - owned(name))
        if foreign:
            yield f"class {module}.{name} is a parent that reads state it does not own: self.{', self.'.join(foreign)}"


def private_imports(trees: dict[str, ast.Module]) -> Iterator[str]:
    for name, tree in trees.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("fbspost")):
                for alias in node.names:
                    if alias.name.startswith("_") and not alias.name.startswith("__"):
                        source = "." * node.level + (node.module or "")
                        yield f"private name imported: {name} imports {alias.name} from {source}"


def imports(trees: dict[str, ast.Module]) -> dict[str, set[str]]:
    """Module -> the project's modules it imports (anywhere in it)."""
    graph = {}
    for name, tree in trees.items():
        package = name if _is_package(name, trees) else name.rpartition(".")[0]
        edges = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                base = package.split(".")[:len(package.split(".")) - node.level + 1] if node.level else []
                target = ".".join(base + ([node.module] if node.module else []))
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    edges.add(sub if sub in trees else target)
            elif isinstance(node, ast.Import):
                edges.update(alias.name for alias in node.names)
        graph[name] = {edge for edge in edges if edge in trees and edge != name}
    return graph


def _is_package(name: str, trees: dict[str, ast.Module]) -> bool:
    return any(other.startswith(name + ".") for other in trees)


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan's algorithm)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for successor in sorted(graph[node]):
            if successor not in index:
                visit(successor)
                low[node] = min(low[node], low[successor])
            elif successor in on_stack:
                low[node] = min(low[node], index[successor])
        if low[node] == index[node]:
            component = []
            while not component or component[-1] != node:
                component.append(stack.pop())
                on_stack.discard(component[-1])
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def package_graph(graph: dict[str, set[str]], top: str) -> dict[str, set[str]]:
    """Each first-level package (or module) of ``top`` -> the others it imports."""
    def package(name: str) -> str:
        return ".".join(name.split(".")[:2])

    folded = {package(name): set() for name in graph if name != top}
    for name, edges in graph.items():
        if name != top:
            folded[package(name)].update(package(edge) for edge in edges
                                         if edge != top and package(edge) != package(name))
    return folded


def lowest_first(graph: dict[str, set[str]]) -> list[str]:
    order, done = [], set()

    def visit(node: str) -> None:
        if node not in done:
            done.add(node)
            for successor in sorted(graph[node]):
                visit(successor)
            order.append(node)

    for node in sorted(graph):
        visit(node)
    return order


def main() -> int:
    trees = modules(ROOT / "fbspost")
    graph = imports(trees)
    packages = package_graph(graph, "fbspost")
    found = [*too_long(trees), *mixins(trees), *private_imports(trees)]
    found += [f"import cycle: {' <-> '.join(component)}" for component in cycles(graph)]
    found += [f"package import cycle: {' <-> '.join(component)}" for component in cycles(packages)]
    for line in found:
        print(line)
    if "--graph" in sys.argv[1:]:
        for name in lowest_first(packages):
            print(f"{name} -> {', '.join(sorted(packages[name])) or '(none)'}")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
