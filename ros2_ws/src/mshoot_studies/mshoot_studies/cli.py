"""The ``mshoot`` command: one entry point, one verb per application.

    mshoot case ou44 --data PATH --horizon 10 --control fmu --out out/case
    mshoot study --data PATH --out docs --jobs 2
    mshoot VERB --help

Each verb's options are those of its module's own ``build_parser`` (so
``python -m mshoot_studies.case`` and ``mshoot case`` take the same
arguments), and the verb runs that module's ``run(args)``. Only the module of
the verb given is imported (``mshoot case`` does not load the study, its
plots or its cluster client).
"""
from __future__ import annotations

import argparse
import atexit
import importlib
import logging
import os
import sys
from typing import Sequence

#: Verbs of ``mshoot``: name -> (module with build_parser(parser) and run(args), summary).
VERBS: dict[str, tuple[str, str]] = {
    'case': ('mshoot_studies.case', 'one closed-loop MPC emulation of the reference case (or '
                                    'the synthetic scenario): KPIs, trajectories, plot'),
    'study': ('mshoot_studies.study', 'the reference study: every table and figure, runs on '
                                      'local worker processes or a Dask cluster'),
}


def build_parser(verbs: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """``mshoot`` with one subparser per verb of :data:`VERBS`.

    Parameters
    ----------
    verbs : sequence of str, optional
        The verbs whose options are needed (their modules are imported); the
        others are listed with their summary only. Default: all.
    """
    parser = argparse.ArgumentParser(
        prog='mshoot', description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    subparsers = parser.add_subparsers(title='verbs', dest='verb', metavar='VERB',
                                       required=True)
    for name, (module_name, summary) in VERBS.items():
        if verbs is not None and name not in verbs:
            subparsers.add_parser(name, help=summary)
            continue
        module = importlib.import_module(module_name)
        verb = subparsers.add_parser(name, help=summary, description=module.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
        module.build_parser(verb)
        verb.set_defaults(run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: the process arguments) and run the verb; its exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    verb = next((word for word in argv if not word.startswith('-')), None)
    args = build_parser([verb] if verb in VERBS else []).parse_args(argv)
    return args.run(args)


def exit_now(code: int) -> None:
    """End the process with ``code`` once everything it wrote is out, without tearing the
    interpreter down module by module (a few hundred ms for the thousand modules of a
    run, spent after the last output).

    What a normal exit does for the files and logs is done first: the ``atexit``
    handlers (``logging.shutdown`` flushes and closes the log handlers, weakref
    finalizers remove temporary folders), then the standard streams are flushed.
    Only for a command's process, after its ``main`` returned: a caller that
    imports the module and calls ``main`` gets its exit code back instead.
    """
    try:
        atexit._run_exitfuncs()  # what Py_Finalize runs first; then it only frees memory
    except Exception:  # noqa: BLE001 - the handlers report their own errors; exit anyway
        logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # closed or broken pipe: nothing more to write
            pass
    os._exit(code)


def console_main() -> None:
    """The ``mshoot`` console script: :func:`main`, then a fast :func:`exit_now`."""
    try:
        code = main()
    except SystemExit as stop:  # argparse errors and --help: as sys.exit would report them
        code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
        if stop.code is not None and not isinstance(stop.code, int):
            print(stop.code, file=sys.stderr)
    exit_now(code)


if __name__ == '__main__':
    console_main()
