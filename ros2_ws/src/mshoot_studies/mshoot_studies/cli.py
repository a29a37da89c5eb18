"""
The ``mshoot`` command: one entry point, one verb per application.

    mshoot case ou44 --data PATH --horizon 10 --control fmu --out out/case
    mshoot case synthetic --control zone.yaml --emulator zone_cs.yaml --out out/zone
    mshoot card check zone.yaml
    mshoot study --data PATH --out docs --jobs 2
    mshoot identify --plant plant.yaml --model model.yaml --out out/identify
    mshoot forecast --testcase DIR --time 0 --temperature-uncertainty high --seed 1
    mshoot boptest --testcase DIR --card CARD.yaml --controllers baseline rule --out OUT
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
import contextlib
import gc
import importlib
import logging
import os
import sys
import threading
from typing import Any, Sequence

#: Verbs of ``mshoot``: name -> (module with build_parser(parser) and run(args), summary).
VERBS: dict[str, tuple[str, str]] = {
    'case': ('mshoot_studies.case', 'one closed-loop MPC emulation of the reference case (or '
                                    'the synthetic scenario): KPIs, trajectories, plot'),
    'study': ('mshoot_studies.study', 'the reference study: every table and figure, runs on '
                                      'local worker processes or a Dask cluster'),
    'card': ('mshoot_studies.card', 'model cards: check a card against its model and print '
                                    "what it maps, list an FMU's variables"),
    'calibrate': ('mshoot_studies.calibrate', 'fit model parameters to measured data (the OU44 '
                                              'reference calibration): RMSEs, card, figure'),
    'identify': ('mshoot_studies.identify', 'identify a control model from a plant: an '
                                            'excitation experiment, then a calibration of a '
                                            'network card; validation RMSEs'),
    'forecast': ('mshoot_studies.forecast', 'the forecast a BOPTEST test case serves at a time, '
                                            "with BOPTEST's forecast uncertainty, as CSV"),
    'boptest': ('mshoot_studies.boptest', 'any BOPTEST test case folder and a card: baseline '
                                          "and rule runs, BOPTEST's KPIs per zone and energy"),
}


#: Environment of a verb's process, set by the console script before any module of the verb
#: loads (a value the user set wins). The case's solves use one BLAS thread (the
#: ``blas_threads`` setting, which the case keeps at 1); a BLAS library that starts with a
#: pool of more threads only burns CPU: every OpenBLAS loaded (numpy's, SciPy's, IPOPT's;
#: the plot worker's) starts its worker threads when it loads and they busy-wait for about
#: 0.1 s, some 0.2-0.3 s of CPU per run for nothing, taken from the run on a busy machine.
VERB_ENVIRONMENT: dict[str, dict[str, str]] = {'case': {'OPENBLAS_NUM_THREADS': '1'}}


#: Verbs that draw a closed-loop figure: the console script starts their plot worker
#: (:class:`mshoot_core.plotting.PlotWorker`) before it loads the verb, so that the worker
#: imports matplotlib while the verb imports and runs.
FIGURE_VERBS = frozenset({'case'})


def verb_parser(parser: argparse.ArgumentParser | None, prog: str,
                description: str | None) -> argparse.ArgumentParser:
    """
    Return ``parser`` (a verb's, from :func:`build_parser`), or a new one for ``python -m prog``.

    Its errors are one line (``<prog>: error: ...``, no usage block) and exit 2. Every parser
    of the verbs is made here: ``mshoot`` itself, each verb's (its module's ``build_parser``
    fills the one it is given, or a new one) and their sub-commands.
    """
    if parser is None:
        parser = argparse.ArgumentParser(prog=f'python -m {prog}', description=description,
                                         formatter_class=argparse.RawDescriptionHelpFormatter)
    name = parser.prog

    def error(message: str) -> None:
        parser.exit(2, f'{name}: error: {message}\n')
    parser.error = error  # type: ignore[method-assign]
    return parser


def _verb(argv: Sequence[str]) -> str | None:
    """Return the verb of a command line (its first word that is not an option), if it is one."""
    word = next((word for word in argv if not word.startswith('-')), None)
    return word if word in VERBS else None


def build_parser(verbs: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """
    ``mshoot`` with one subparser per verb of :data:`VERBS`.

    Parameters
    ----------
    verbs : sequence of str, optional
        The verbs whose options are needed (their modules are imported); the
        others are listed with their summary only. Default: all.

    """
    parser = verb_parser(argparse.ArgumentParser(
        prog='mshoot', description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter), 'mshoot', __doc__)
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


def main(argv: Sequence[str] | None = None, plot_worker: Any = None) -> int:
    """
    Parse ``argv`` (default: the process arguments) and run the verb; its exit code.

    ``plot_worker``, a started :class:`mshoot_core.plotting.PlotWorker`, is handed to a
    verb of :data:`FIGURE_VERBS` (as ``args.plot_worker``); without it the verb starts its
    own.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    verb = _verb(argv)
    args = build_parser([verb] if verb else []).parse_args(argv)
    if plot_worker is not None:
        args.plot_worker = plot_worker
    return args.run(args)


def exit_now(code: int) -> None:
    """
    End the process with ``code`` once everything it wrote is out.

    Without tearing the interpreter down module by module (a few hundred ms for the thousand
    modules of a run, spent after the last output).

    What a normal exit does for the files and logs is done first: the ``atexit``
    handlers (``logging.shutdown`` flushes and closes the log handlers, weakref
    finalizers remove temporary folders), then the standard streams are flushed.
    Only for a command's process, after its ``main`` returned: a caller that
    imports the module and calls ``main`` gets its exit code back instead. While
    a thread other than daemons is still running (a pool the verb did not shut
    down), the normal exit waits for it: ``sys.exit``.
    """
    if any(thread.is_alive() and not thread.daemon and thread is not threading.main_thread()
           for thread in threading.enumerate()):
        sys.exit(code)
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


#: Exit code when the reader of stdout closed the pipe early (as a process killed by SIGPIPE).
BROKEN_PIPE_EXIT = 141


def reader_gone() -> int:
    """
    Quietly end the output of a command whose reader closed the pipe (``| head``).

    Points stdout at ``/dev/null``, so that no later flush raises (and no traceback or
    "Exception ignored" appears); returns :data:`BROKEN_PIPE_EXIT`.
    """
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    finally:
        os.close(devnull)
    return BROKEN_PIPE_EXIT


def import_verb(verb: str) -> None:
    """
    Import the module of a verb without the cyclic garbage collector, then freeze its objects.

    An import makes a few hundred thousand objects (numpy, pandas, the models) and no garbage
    worth collecting, while the collector, run every 700 allocations, traverses them again
    and again: some 35 ms of CPU of a ``mshoot case`` command. Frozen
    (:func:`gc.freeze`), they are left out of the run's later collections too. For the
    command's process only (:func:`console_main`): frozen objects are never collected.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        importlib.import_module(VERBS[verb][0])
    finally:
        gc.freeze()
        if enabled:
            gc.enable()


def console_main() -> None:
    """
    Run the ``mshoot`` console script.

    The verb's :data:`VERB_ENVIRONMENT`, its module imported (:func:`import_verb`),
    :func:`main`, then a fast :func:`exit_now`.
    """
    verb = _verb(sys.argv[1:])
    for name, value in VERB_ENVIRONMENT.get(verb, {}).items():
        os.environ.setdefault(name, value)
    with contextlib.ExitStack() as stack:
        worker = None
        if verb in FIGURE_VERBS:
            from mshoot_core.plotting import PlotWorker  # the standard library only
            worker = stack.enter_context(PlotWorker())
        if verb is not None:
            import_verb(verb)
        try:
            code = main(plot_worker=worker)
        except BrokenPipeError:  # `mshoot card check ... | head`: the reader has had enough
            code = reader_gone()
        except SystemExit as stop:  # argparse errors and --help: as sys.exit reports them
            code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
            if stop.code is not None and not isinstance(stop.code, int):
                print(stop.code, file=sys.stderr)
    exit_now(code)


if __name__ == '__main__':
    console_main()
