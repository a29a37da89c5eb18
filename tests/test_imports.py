"""
No import circles: no module of a package imports (directly or through others) itself.

Every ``import`` counts, at module level and inside functions (a lazy import only hides a
circle), except those under ``if TYPE_CHECKING:``. The packages' sources are read as text
(``ast``): nothing is imported.
"""
import ast
import pathlib

import pytest

SOURCES = pathlib.Path(__file__).resolve().parents[1] / 'ros2_ws' / 'src'
PACKAGES = ('mshoot_core', 'mshoot_nodes', 'mshoot_studies')


def module_files(package: str) -> dict[str, pathlib.Path]:
    """Return the package's modules by dotted name."""
    root = SOURCES / package / package
    modules = {}
    for path in sorted(root.rglob('*.py')):
        parts = path.relative_to(root.parent).with_suffix('').parts
        if parts[-1] == '__init__':
            parts = parts[:-1]
        modules['.'.join(parts)] = path
    return modules


def imported(name: str, path: pathlib.Path, modules: dict[str, pathlib.Path]) -> set[str]:
    """Return the modules of ``modules`` that the module ``name`` imports."""
    tree = ast.parse(path.read_text(encoding='utf-8'))
    hidden = {id(sub) for node in ast.walk(tree)
              if isinstance(node, ast.If) and 'TYPE_CHECKING' in ast.unparse(node.test)
              for sub in ast.walk(node)}
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    found = set()
    for node in ast.walk(tree):
        if id(node) in hidden:
            continue
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                anchor = package.split('.')[:len(package.split('.')) - node.level + 1]
                base = '.'.join([*anchor, *([base] if base else [])])
            for alias in node.names:
                full = f'{base}.{alias.name}'
                found.add(full if full in modules else base)
    return {m for m in found if m in modules and m != name}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Return the strongly connected groups of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for other in sorted(graph[node]):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                out.append(sorted(group))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return out


@pytest.mark.parametrize('package', PACKAGES)
def test_no_import_circles(package):
    modules = module_files(package)
    graph = {name: imported(name, path, modules) for name, path in modules.items()}
    assert graph, package
    assert circles(graph) == []


def test_the_check_finds_a_circle():
    """Two modules that import each other (one lazily) are one circle."""
    assert circles({'a': {'b'}, 'b': {'a'}, 'c': {'a'}}) == [['a', 'b']]
    assert circles({'a': {'b'}, 'b': set()}) == []
