"""
Mechanical fixes for the ament linters (tests/test_lint.py): docstring layout and import groups.

    python tools/ament_layout.py [--application NAMES] FILE...

Docstrings: a multi-line docstring gets its summary on the line after the opening quotes
(pep257 D213, ament keeps it), its closing quotes on a line of their own (D209) and, when it
has numpydoc sections, a blank line after the last one (D413). With ``--application`` (the
folder's own top-level modules, comma-separated, as in ``LINTED`` of tests/test_lint.py),
each run of module-level imports is regrouped in google order: standard library, third party
(the workspace's other packages included), then the application, each sorted by module name
(flake8-import-order I100/I201). A run with a comment inside is left alone and reported.

Only layout changes: the text of a docstring, the wording of a summary line (D401 imperative
mood, D205/D400 one-sentence summary) and the names inside a ``from`` import (I101) are left
to the author. Run the lint test afterwards for what remains.
"""
import argparse
import ast
import pathlib
import re
import sys

SECTION = re.compile(r'^\s*(Parameters|Returns|Yields|Receives|Raises|Warns|Warnings|Notes|'
                     r'Examples|See Also|References|Attributes|Methods|Other Parameters)\s*$')
UNDERLINE = re.compile(r'^\s*-{3,}\s*$')
OPENING = re.compile(r'([rRuU]*)("""|\'\'\')')


def _docstring_nodes(tree: ast.Module) -> list[ast.Constant]:
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            first = node.body[0] if node.body else None
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) \
                    and isinstance(first.value.value, str):
                found.append(first.value)
    return found


def _char_column(line: str, byte_offset: int) -> int:
    return len(line.encode()[:byte_offset].decode())


def _has_sections(lines: list[str]) -> bool:
    return any(SECTION.match(a) and UNDERLINE.match(b) for a, b in zip(lines, lines[1:]))


def docstring_layout(text: str) -> str:
    """
    Return ``text`` with every multi-line docstring laid out as ament's pep257 wants.

    Parameters
    ----------
    text : str
        Python source.

    Returns
    -------
    str
        The source with only the layout of multi-line docstrings changed.

    """
    lines = text.split('\n')
    edits = []
    for node in _docstring_nodes(ast.parse(text)):
        first, last = node.lineno - 1, node.end_lineno - 1
        start = lines[first]
        column = _char_column(start, node.col_offset)
        opening = OPENING.match(start, column)
        if first == last or not opening or start[:column].strip():
            continue
        indent = ' ' * column
        end_line = lines[last]
        end_column = _char_column(end_line, node.end_col_offset)
        content = [start[opening.end():]] + lines[first + 1:last] + [end_line[:end_column - 3]]
        if not content[0].strip():
            content = content[1:]
        else:
            content[0] = indent + content[0].lstrip()
        while content and not content[-1].strip():
            content.pop()
        if _has_sections(content):
            content.append('')
        new = ([start[:opening.end()]] + [s.rstrip() for s in content]
               + [indent + end_line[end_column - 3:]])
        if new != lines[first:last + 1]:
            edits.append((first, last, new))
    for first, last, new in sorted(edits, reverse=True):
        lines[first:last + 1] = new
    return '\n'.join(lines)


def _name_key(name: str) -> tuple[str, str]:
    return name.lower(), name


def _group(node: ast.Import | ast.ImportFrom, application: set[str]) -> int:
    if isinstance(node, ast.ImportFrom) and node.level:
        return 4
    module = node.module if isinstance(node, ast.ImportFrom) else node.names[0].name
    top = module.split('.')[0]
    if module == '__future__':
        return 0
    if top in application:
        return 3
    return 1 if top in sys.stdlib_module_names else 2


def _sort_key(node: ast.Import | ast.ImportFrom) -> tuple[list, list]:
    if isinstance(node, ast.ImportFrom):
        return [_name_key(node.module or '')], [_name_key(a.name) for a in node.names]
    return [_name_key(a.name) for a in node.names], []


def import_groups(text: str, application: set[str], where: str = '') -> str:
    """
    Return ``text`` with each run of module-level imports in google order.

    Parameters
    ----------
    text : str
        Python source.
    application : set of str
        Top-level modules of the application group (the last one).
    where : str
        Name of the source in the messages about runs left alone.

    Returns
    -------
    str
        The source with only the order and grouping of import statements changed.

    """
    lines = text.split('\n')
    runs, run = [], []
    for node in ast.parse(text).body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            run.append(node)
            continue
        runs.append(run)
        run = []
    runs.append(run)
    edits = []
    for run in (r for r in runs if len(r) > 1):
        first, last = run[0].lineno - 1, run[-1].end_lineno - 1
        covered = {i for node in run for i in range(node.lineno - 1, node.end_lineno)}
        if any(lines[i].strip() for i in range(first, last + 1) if i not in covered):
            print(f'{where}:{first + 1}: comment or code among the imports, left alone',
                  file=sys.stderr)
            continue
        groups: dict[int, list] = {}
        for node in run:
            groups.setdefault(_group(node, application), []).append(
                (_sort_key(node), lines[node.lineno - 1:node.end_lineno]))
        new: list[str] = []
        for kind in sorted(groups):
            new.extend([''] if new else [])
            for _, statement in sorted(groups[kind], key=lambda item: item[0]):
                new.extend(statement)
        if new != lines[first:last + 1]:
            edits.append((first, last, new))
    for first, last, new in sorted(edits, reverse=True):
        lines[first:last + 1] = new
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """Rewrite the files given; print the ones changed."""
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('files', nargs='+', type=pathlib.Path)
    parser.add_argument('--application', default='',
                        help='comma-separated top-level modules of the last import group; '
                             'imports are regrouped only when given')
    args = parser.parse_args(argv)
    application = {name for name in args.application.split(',') if name}
    for path in args.files:
        old = path.read_text()
        new = docstring_layout(old)
        if application:
            new = import_groups(new, application, str(path))
        if new != old:
            path.write_text(new)
            print(path)
    return 0


if __name__ == '__main__':
    sys.exit(main())
