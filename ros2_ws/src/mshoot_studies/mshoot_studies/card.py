"""
Model cards from the command line: check a card against its model, list an FMU's variables.

    mshoot card check CARD.yaml      # validate; print what the card maps (exit 2: every problem)
    mshoot card variables MODEL.fmu  # every variable of an FMU: causality, type, unit, start

``card check`` validates the card against the JSON Schema and against its model, with the
modelDescription validated as a run validates it (a card's ``validate: false`` relaxes
both), and loads the FMU's binary once in a child process, with the card's ``preload``
libraries, as a run will (a missing library is named, with how to provide it; a damaged
binary is one line, not a signal). Exit codes: 0 the card is good; 2 every problem, on
stderr (a long list: the first 20 and the count).

A card (YAML, see :mod:`mshoot_core.models.card`) describes a zone model once
for the case command (``mshoot case ... --control CARD.yaml --emulator
CARD.yaml``), the Python API and the ROS nodes. The built-in cards are in
``mshoot_core/cards/``.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
from typing import Sequence, TextIO

from mshoot_core.models import card as cards
from mshoot_core.models.fmu_variables import fmu_variables
from mshoot_core.models.registry import CONTROL_TOLERANCE, EMULATOR_TOLERANCE

from mshoot_studies.cli import verb_parser

#: Longest list of a card's problems printed by ``card check`` (then their count).
MAX_PROBLEMS = 20
#: Columns of the mapping table of ``card check``.
COLUMNS = (('section', 'section'), ('name', 'name'), ('variable', 'model variable'),
           ('causality', 'causality'), ('unit', 'unit'), ('canonical', 'canonical'),
           ('conversion', 'conversion'), ('notes', 'notes'))


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """
    Build the command line of the card tools.

    Fills ``parser`` (the ``card`` verb of ``mshoot``), or a new parser when None.
    Its errors are one line (``<prog>: error: ...``) and exit 2
    (:func:`~mshoot_studies.cli.verb_parser`).
    """
    parser = verb_parser(parser, 'mshoot_studies.card', __doc__)
    actions = parser.add_subparsers(title='actions', dest='action', metavar='ACTION',
                                    required=True)
    check = verb_parser(actions.add_parser(
        'check', help='validate a model card against its model and print what it maps (exit 2 '
                      'with every problem)'), 'mshoot_studies.card', None)
    check.add_argument('card', type=pathlib.Path, help='the model card (.yaml)')
    listing = verb_parser(actions.add_parser(
        'variables', help="list an FMU's variables (name, causality, type, unit, start), to "
                          'write a card'), 'mshoot_studies.card', None)
    listing.add_argument('fmu', type=pathlib.Path, help='the FMU (.fmu file or folder)')
    listing.add_argument('--causality', default=None,
                         help='only variables of this causality (input, output, parameter, '
                              'local, ...; default: every causality)')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: the process arguments) and run; the exit code."""
    return run(build_parser().parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """Run the action parsed by :func:`build_parser`: 0, or 2 on a bad card or FMU."""
    if args.action == 'variables':
        return list_variables(args.fmu, args.causality, sys.stdout, sys.stderr)
    return check(args.card, sys.stdout, sys.stderr)


def check(path: pathlib.Path, out: TextIO, err: TextIO) -> int:
    """
    Validate the card at ``path``.

    Print its mapping to ``out`` (0) or every problem to ``err`` (2).
    """
    try:
        card = cards.load_card(path)
        preloaded = cards.check_binary(card)
    except cards.CardError as exc:
        count = len(exc.problems)
        err.write(f'model card {exc.path}: {count} problem{"s" if count != 1 else ""}\n')
        err.write(''.join(f'  - {problem}\n' for problem in exc.problems[:MAX_PROBLEMS]))
        if count > MAX_PROBLEMS:
            err.write(f'  ... and {count - MAX_PROBLEMS} more (the first {MAX_PROBLEMS} '
                      'shown)\n')
        return 2
    out.write(f'model card {card.path}: OK\n')
    if card.description:
        out.write(f'  {card.description}\n')
    if card.network is not None:
        net = card.network
        free = [f'{p.name} [{p.min:g}, {p.max:g}]' for p in net.free_parameters]
        out.write(f"model: {f'builtin {card.builtin}: ' if card.builtin else ''}a thermal "
                  f'network (exact per-interval solution): nodes {list(net.nodes)}, '
                  f'{len(net.conductances)} conductances, {len(net.gains)} gains; free '
                  f"parameters: {', '.join(free) or 'none'}\n")
    else:
        what = f'builtin {card.builtin}: ' if card.builtin else ''
        out.write(f'model: {what}{card.fmu} as {card.interface} (fmi_type {card.fmi_type})\n')
        tolerance = (f'{card.tolerance:g}' if card.tolerance is not None else
                     f'that of the role (control {CONTROL_TOLERANCE:g}, emulator '
                     f'{EMULATOR_TOLERANCE:g})')
        out.write(f'tolerance: {tolerance}; time origin: {card.time_origin}\n')
        out.write('binary: loads in a test process'
                  + (f' (preloading {", ".join(preloaded)})' if preloaded else '')
                  + ('' if card.validate else '; modelDescription not validated '
                     '(validate: false)') + '\n')
    if card.parameters:
        out.write('parameters: ' + ', '.join(f'{k} = {v!r}' for k, v in card.parameters.items())
                  + '\n')
    rows = cards.describe(card)
    widths = {key: max(len(title), *(len(r[key]) for r in rows)) for key, title in COLUMNS}
    line = '  '.join(title.ljust(widths[key]) for key, title in COLUMNS)
    out.write(line.rstrip() + '\n')
    for row in rows:
        out.write('  '.join(row[key].ljust(widths[key]) for key, _ in COLUMNS).rstrip() + '\n')
    out.write(f'model inputs: {list(card.input_names)} (controls {list(card.control_names)}); '
              f'states: {list(card.state_names)}; outputs: {list(card.output_names)}\n')
    return 0


def list_variables(path: pathlib.Path, causality: str | None, out: TextIO,
                   err: TextIO) -> int:
    """Print every variable of the FMU at ``path`` (0), or why it cannot be read (2)."""
    import fmpy
    if not path.exists():
        err.write(f'FMU not found: {path}\n')
        return 2
    try:
        md = fmpy.read_model_description(str(path), validate=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable FMU: one line, exit 2
        err.write(f'cannot read the model description of {path}: {" ".join(str(exc).split())}\n')
        return 2
    interfaces = [name for name, kind in (('Model Exchange', md.modelExchange),
                                          ('Co-Simulation', md.coSimulation)) if kind]
    out.write(f'{path}: FMI {md.fmiVersion}, {md.modelName}, {" and ".join(interfaces)}\n')
    rows = [v for v in fmu_variables(md)
            if causality is None or v.causality.split(',')[0] == causality]
    header = ('name', 'causality', 'variability', 'type', 'unit', 'start')
    table = [(v.name, v.causality, v.variability, v.type, v.unit,
              '' if v.start is None else f'{v.start:g}') for v in rows]
    widths = [max(len(h), *(len(r[i]) for r in table)) if table else len(h)
              for i, h in enumerate(header)]
    for row in (header, *table):
        out.write('  '.join(c.ljust(w) for c, w in zip(row, widths)).rstrip() + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
