"""
Sphinx extension of the mshoot documentation: tables and listings generated from the code.

Nothing here is written twice: the settings table is :data:`mshoot_core.settings.PARAMETERS`,
a node's parameters are its module's ``PARAMS``, the topics and their QoS are
:mod:`mshoot_nodes.contract`, the messages are the ``.msg`` files of ``mshoot_msgs``, and the
command line is the ``--help`` of each parser, formatted at build time.

Directives (MyST: ```` ```{mshoot-settings} ```` ... ```` ``` ````):

``mshoot-settings``
    Every described setting of the controller, one table per group (default, range or
    choices, what a change at run time implies, unit and description, the ``mshoot case``
    option where it has one); each is a parameter of the MPC node of the same name. Option
    ``:groups:`` limits the tables to some groups (e.g. ``problem comfort``); ``:model:`` (a
    flag) lists the model settings of :mod:`mshoot_core.models.registry` instead.
``mshoot-node-params`` *module*
    The parameters a node declares (its module's ``PARAMS``): type, default, range or
    choices, read-only, description.
``mshoot-topics``
    The topic contract: name, message type, QoS.
``mshoot-messages``
    Every ``.msg`` file of ``mshoot_msgs``, one section each, verbatim.
``mshoot-help`` *module:function* or *command*
    The ``--help`` of an argparse parser (``module:function`` returning it; every sub-command
    too, one section each) or of a command run with ``--help``.
``mshoot-api`` *package*
    One section per module of the package (recursively) with its ``automodule`` (the members
    the module defines: re-exports are documented where they are defined); option
    ``:exclude:`` leaves out modules (and their submodules) by name. Docstrings may write an
    absolute value as ``|x|``: it is escaped, not read as an RST substitution.

The ``index`` page's toctree line ``%REMAINING%`` becomes the top-level pages no toctree of
the index names (pages added by other branches land there until placed in a section).
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import pathlib
import pkgutil
import re
import shlex
import subprocess
import sys
from typing import Any, Iterator

from docutils import nodes
from docutils.parsers.rst import directives
from docutils.statemachine import StringList
from sphinx.application import Sphinx
from sphinx.util.docutils import SphinxDirective
from sphinx.util.nodes import nested_parse_with_titles

#: Width of the generated ``--help`` texts [characters].
HELP_COLUMNS = 96
#: The ``mshoot_msgs`` package's message folder, relative to the repository root.
MSG_DIR = pathlib.Path('ros2_ws/src/mshoot_msgs/msg')


def _literal(text: str) -> str:
    """Return ``text`` as an inline literal of a list-table cell (RST)."""
    text = str(text).replace('`', "'")
    return f'``{text}``' if text else ''


def _cell(text: str) -> str:
    """Escape what RST would read as markup in a plain table cell."""
    return str(text).replace('\\', '\\\\').replace('*', r'\*').replace('|', r'\|') \
        .replace('`', "'").replace('_ ', r'\_ ')


def _bounds(low: Any, high: Any, choices: tuple[str, ...]) -> str:
    if choices:
        return ', '.join(_literal(c) for c in choices)
    if low is None and high is None:
        return ''
    lo = '-inf' if low is None else f'{low:g}'
    hi = 'inf' if high is None else f'{high:g}'
    return f'[{lo}, {hi}]'


def list_table(header: list[str], rows: list[list[str]], widths: str = 'auto') -> list[str]:
    """Return the lines of an RST list-table."""
    lines = ['.. list-table::', '   :header-rows: 1', f'   :widths: {widths}', '']
    for row in [header, *rows]:
        lines.append('   * - ' + (row[0] or ' '))
        lines += ['     - ' + (cell or ' ') for cell in row[1:]]
    return lines


class RstDirective(SphinxDirective):
    """A directive whose output is RST text parsed in place (sections allowed)."""

    def rst(self) -> list[str]:
        raise NotImplementedError

    def run(self) -> list[nodes.Node]:
        node = nodes.section()
        node.document = self.state.document
        source = self.get_source_info()[0]
        lines = self.rst()
        if 'myst' in type(self.state).__module__:  # a MyST page parses Markdown: RST inside
            lines = ['````{eval-rst}', *lines, '````']
        nested_parse_with_titles(self.state, StringList(lines, source=source), node)
        # what the text came from: an incremental build re-reads the page when the code changes
        for module in list(sys.modules.values()):
            path = getattr(module, '__file__', None)
            if path and module.__name__.split('.')[0].startswith('mshoot_'):
                self.env.note_dependency(path)
        return node.children


class SettingsTable(RstDirective):
    """The controller's settings, from :data:`mshoot_core.settings.PARAMETERS`."""

    option_spec = {'groups': directives.unchanged, 'model': directives.flag}

    def rst(self) -> list[str]:
        from mshoot_core import settings
        from mshoot_studies.case import CASE_SETTINGS
        if 'model' in self.options:
            from mshoot_core.models.registry import MODEL_PARAMETERS, ModelSettings
            tables = [(None, ModelSettings, MODEL_PARAMETERS)]
        else:
            wanted = (self.options.get('groups') or '').split()
            tables = [(name, cls, settings.fields_of(cls))
                      for name, cls in settings.GROUPS.items() if not wanted or name in wanted]
        lines: list[str] = []
        for name, cls, fields in tables:
            rows = []
            for f in fields:
                description = _cell(f.description)
                if f.name in CASE_SETTINGS:
                    option = f.cli or '--' + f.name.replace('_', '-')
                    description += f' (``mshoot case {option}``)'
                rows.append([_literal(f.name), _literal(repr(f.default)),
                             _bounds(f.low, f.high, f.choices),
                             _literal('; '.join(sorted(f.applies))), description])
            if name is not None:
                title = f'Group ``{name}``'
                summary = (cls.__doc__ or '').strip().splitlines()[0]
                lines += [title, '~' * len(title), '', _cell(summary), '']
            lines += list_table(['setting', 'default', 'range or choices', 'run-time change',
                                 'description [unit]'], rows, widths='22 12 16 12 38')
            lines.append('')
        return lines


class NodeParams(RstDirective):
    """The parameters one node declares (its module's ``PARAMS``)."""

    required_arguments = 1

    def rst(self) -> list[str]:
        module = importlib.import_module(self.arguments[0])
        rows = []
        for spec in module.PARAMS:
            rows.append([_literal(spec.name), _literal(repr(spec.default)),
                         _bounds(spec.low, spec.high, spec.choices),
                         'yes' if spec.read_only else '', _cell(spec.description)])
        return list_table(['parameter', 'default', 'range or choices', 'read-only',
                           'description [unit]'], rows, widths='24 14 16 8 38')


def _qos_words(qos: Any) -> str:
    reliability = qos.reliability.name.lower().replace('_', ' ')
    durability = qos.durability.name.lower().replace('_', ' ')
    return f'{reliability}, {durability}, depth {qos.depth}'


class Topics(RstDirective):
    """The topic contract of :mod:`mshoot_nodes.contract`."""

    def rst(self) -> list[str]:
        from mshoot_nodes import contract
        rows = [[_literal(topic), _literal(kind), _qos_words(contract.TOPIC_QOS[topic])]
                for topic, kind in contract.TOPIC_TYPES.items()]
        return list_table(['topic', 'type', 'QoS (offered)'], rows)


def _repo_root(app: Sphinx) -> pathlib.Path:
    return pathlib.Path(app.srcdir).resolve().parent


class Messages(RstDirective):
    """Every message of ``mshoot_msgs``, verbatim, one section each."""

    def rst(self) -> list[str]:
        folder = _repo_root(self.env.app) / MSG_DIR
        lines: list[str] = []
        for path in sorted(folder.glob('*.msg')):
            self.env.note_dependency(str(path))
            title = f'mshoot_msgs/msg/{path.stem}'
            lines += [title, '~' * len(title), '', '.. code-block:: text', '']
            lines += ['   ' + line if line else '' for line in
                      path.read_text(encoding='utf-8').splitlines()]
            lines.append('')
        return lines


@contextlib.contextmanager
def _columns(width: int) -> Iterator[None]:
    old = os.environ.get('COLUMNS')
    os.environ['COLUMNS'] = str(width)
    try:
        yield
    finally:
        if old is None:
            del os.environ['COLUMNS']
        else:
            os.environ['COLUMNS'] = old


def _parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    """Yield ``parser`` and every sub-command's parser, depth first."""
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):
                yield from _parsers(sub)


class Help(RstDirective):
    """The ``--help`` of a parser and its sub-commands, or of a command."""

    required_arguments = 1
    final_argument_whitespace = True

    def rst(self) -> list[str]:
        target = self.arguments[0]
        lines: list[str] = []
        if ':' in target and ' ' not in target:
            module_name, function = target.split(':')
            parser = getattr(importlib.import_module(module_name), function)()
            with _columns(HELP_COLUMNS):
                helps = [(p.prog, p.format_help()) for p in _parsers(parser)]
        else:
            command = shlex.split(target) + ['--help']
            env = {**os.environ, 'COLUMNS': str(HELP_COLUMNS)}
            done = subprocess.run(command, capture_output=True, text=True, env=env,
                                  cwd=_repo_root(self.env.app), timeout=120, check=False)
            if done.returncode != 0:
                raise self.error(f'{target} --help exited {done.returncode}: {done.stderr}')
            helps = [(target, done.stdout)]
        for prog, text in helps:
            title = f'``{prog}``'
            lines += [title, '~' * len(title), '', '.. code-block:: text', '']
            lines += ['   ' + line if line.strip() else '' for line in text.splitlines()]
            lines.append('')
        return lines


def _modules(package: str, exclude: tuple[str, ...]) -> list[str]:
    root = importlib.import_module(package)
    names = [package]
    for info in pkgutil.walk_packages(root.__path__, package + '.'):
        names.append(info.name)
    return sorted(n for n in names
                  if not any(n == e or n.startswith(e + '.') for e in exclude))


class Api(RstDirective):
    """One ``automodule`` section per module of a package."""

    required_arguments = 1
    option_spec = {'exclude': directives.unchanged}

    def rst(self) -> list[str]:
        exclude = tuple((self.options.get('exclude') or '').split())
        lines: list[str] = []
        for name in _modules(self.arguments[0], exclude):
            title = f'``{name}``'
            lines += [title, '~' * len(title), '', f'.. automodule:: {name}',
                      '   :members:', '   :show-inheritance:', '   :ignore-module-all:', '']
        return lines


#: A toctree entry of the index page (a docname alone on its line).
_ENTRY = re.compile(r'^\s*/?([\w./-]+)\s*$', re.M)


def remaining_pages(app: Sphinx, docname: str, source: list[str]) -> None:
    """Replace ``%REMAINING%`` on the index with the top-level pages it does not name."""
    if docname != 'index' or '%REMAINING%' not in source[0]:
        return
    text = source[0]
    named = set()
    for block in re.findall(r'```\{toctree\}(.*?)```', text, re.S):
        named.update(_ENTRY.findall(block))
    srcdir = pathlib.Path(app.srcdir)
    pages = sorted(p.stem for p in srcdir.glob('*.md')
                   if p.stem not in named and p.stem != 'index')
    source[0] = text.replace('%REMAINING%', '\n'.join(pages))


#: ``|x|`` in a docstring (an absolute value, a norm) that RST would read as a substitution.
_BARS = re.compile(r'(?<![\\|])\|(?=[^|\s])([^|`]*?[^|\s])\|(?!\|)')


def escape_bars(app: Sphinx, what: str, name: str, obj: Any, options: Any,
                lines: list[str]) -> None:
    """Escape ``|x|`` in docstrings (mathematics, not RST substitutions), in place."""
    for i, line in enumerate(lines):
        cells = line.strip()
        table_row = cells.startswith(('+-', '+=')) or (
            cells.startswith('|') and cells.endswith('|') and cells.count('|') > 2)
        if '|' in line and not table_row:
            lines[i] = _BARS.sub(r'\\|\1\\|', line)


def prose_attributes(app: Sphinx, what: str, name: str, obj: Any, options: Any,
                     lines: list[str]) -> None:
    """
    Keep a data or attribute docstring prose (before napoleon reads it).

    napoleon reads the first line of such a docstring as ``type: description`` when it holds a
    colon, so ``#: Robust losses of least_squares ('linear': plain ...)`` would lose its start
    to a type. mshoot's types are annotations, never written there: an empty RST comment
    (``..``) as the first line, which napoleon takes for that line, keeps the text whole.
    """
    if what in ('data', 'attribute') and lines and ':' in lines[0]:
        lines[:0] = ['..', '']


def reread_index(app: Sphinx, env: Any, added: set[str], changed: set[str],
                 removed: set[str]) -> list[str]:
    """Re-read the index when pages come or go (its remaining pages change)."""
    return ['index'] if added or removed else []


def setup(app: Sphinx) -> dict[str, Any]:
    """Register the directives and the index hook."""
    app.add_directive('mshoot-settings', SettingsTable)
    app.add_directive('mshoot-node-params', NodeParams)
    app.add_directive('mshoot-topics', Topics)
    app.add_directive('mshoot-messages', Messages)
    app.add_directive('mshoot-help', Help)
    app.add_directive('mshoot-api', Api)
    app.connect('source-read', remaining_pages)
    app.connect('env-get-outdated', reread_index)
    app.connect('autodoc-process-docstring', escape_bars)
    app.connect('autodoc-process-docstring', prose_attributes, priority=400)  # before napoleon
    return {'version': '1', 'parallel_read_safe': True, 'parallel_write_safe': True}
