"""
The ``mshoot`` command: one entry point, one verb per application.

    mshoot case ou44 --data PATH --horizon 10 --control fmu --out out/case
    mshoot study --data PATH --out docs --jobs 2
    mshoot VERB --help

Each verb's options are those of its module's own ``build_parser`` (so
``python -m mshoot_studies.case`` and ``mshoot case`` take the same
arguments), and the verb runs that module's ``run(args)``.
"""
from __future__ import annotations

import argparse
import sys
from types import ModuleType
from typing import Sequence

from mshoot_studies import case, study

#: Verbs of ``mshoot``: name -> (module with build_parser(parser) and run(args), summary).
VERBS: dict[str, tuple[ModuleType, str]] = {
    'case': (case, 'one closed-loop MPC emulation of the reference case (or the synthetic '
                   'scenario): KPIs, trajectories, plot'),
    'study': (study, 'the reference study: every table and figure, runs on local worker '
                     'processes or a Dask cluster'),
}


def build_parser() -> argparse.ArgumentParser:
    """``mshoot`` with one subparser per verb of :data:`VERBS`."""
    parser = argparse.ArgumentParser(
        prog='mshoot', description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    verbs = parser.add_subparsers(title='verbs', dest='verb', metavar='VERB', required=True)
    for name, (module, summary) in VERBS.items():
        verb = verbs.add_parser(name, help=summary, description=module.__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
        module.build_parser(verb)
        verb.set_defaults(run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: the process arguments) and run the verb; its exit code."""
    args = build_parser().parse_args(argv)
    return args.run(args)


if __name__ == '__main__':
    sys.exit(main())
