"""
Build the project's FMI 2.0 FMUs and batch drivers from the C sources in ``fmu_src/``.

Two models ship as C sources:

- ``r1c1``: the R1C1 zone of the OU44 reference case (Model Exchange and
  Co-Simulation in one binary, FMU state get/set/serialise, directional
  derivatives; ``fmi2DoStep`` is the exact per-step solution);
- ``r2c2``: a two-node air + wall zone written in another style (Model
  Exchange only, no FMU state), used by the tests to show that any FMI 2.0 FMU
  works through :class:`mshoot_core.models.fmi.FmiModel`.

Each model's C file holds what is its own (variables, equations, steps) and includes
``fmi2_model.h``, the FMI 2.0 functions every mshoot FMU shares (instance, life cycle,
logging, FMU state, the Model Exchange and Co-Simulation calls around the model's own).
There are two batch drivers too (``cs_batch.c``, ``me_batch.c``) that
:class:`~mshoot_core.models.fmi.FmiModel` loads with ctypes
(:mod:`mshoot_core.models.fmi_drivers`).

This is the build side: ``make setup`` runs ``--cache r1c1``, which compiles
the R1C1 FMU and both drivers into the cache of :mod:`mshoot_core.fmu_cache`
(``$MSHOOT_FMU_DIR``, default ``~/.cache/mshoot/fmu``) unless they are already
built for the current sources; the runtime only finds them there and never
imports this module. It needs only the standard library and a C compiler
(``$CC``, default ``gcc``).

Command line::

    python -m mshoot_core.fmu_build --out DIR [MODEL ...]   # build FMUs into DIR
    python -m mshoot_core.fmu_build --cache [MODEL ...]     # FMUs + drivers into the cache
"""
from __future__ import annotations

import argparse
import datetime
import logging
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
from typing import Sequence
import uuid
import zipfile

from mshoot_core.fmu_cache import (CACHE_ENV, cached_driver_file, cached_fmu_file,
                                   driver_source, DRIVERS, model_source, MODELS, platform,
                                   SOURCE_DIR, source_hash)

logger = logging.getLogger(__name__)

#: Compiler flags; -fvisibility=hidden leaves only the FMI functions exported.
CFLAGS = ('-shared', '-fPIC', '-O2', '-std=c99', '-Wall', '-fvisibility=hidden')


def _guid(name: str) -> str:
    """Return a GUID derived from the sources: the same sources give the same GUID."""
    token = f'mshoot-fmu:{name}:{source_hash(name)}'
    return '{' + str(uuid.uuid5(uuid.NAMESPACE_URL, token)) + '}'


def find_compiler() -> str:
    """
    Return the C compiler to use (``$CC`` or ``gcc``).

    Raises
    ------
    RuntimeError
        If the compiler is not on PATH.

    """
    compiler = os.environ.get('CC') or 'gcc'
    found = shutil.which(compiler)
    if found is None:
        raise RuntimeError(
            f'C compiler {compiler!r} not found on PATH: building the mshoot FMUs needs gcc '
            f'(Debian/Ubuntu: apt-get install gcc), or set CC to another compiler, or prebuild '
            f'them elsewhere and point {CACHE_ENV} at the directory')
    return found


def compile_library(c_file: pathlib.Path, library: pathlib.Path, what: str,
                    defines: Sequence[str] = ()) -> str:
    """
    Compile the C file ``c_file`` into the shared library ``library``.

    With :data:`CFLAGS`, ``defines`` (e.g. ``-DMODEL_GUID="{...}"``) and the headers of
    :data:`~mshoot_core.fmu_cache.SOURCE_DIR` (the FMI 2.0 ones and ``fmi2_model.h``).

    Parameters
    ----------
    c_file, library : pathlib.Path
        The source compiled and the library written.
    what : str
        What is compiled, for messages (e.g. ``'the r1c1 FMU'``).
    defines : sequence of str
        More compiler arguments.

    Returns
    -------
    str
        The compiler's warnings ('' for none; logged too).

    Raises
    ------
    RuntimeError
        If the compiler is missing or the compilation fails.

    """
    command = [find_compiler(), *CFLAGS, *defines, '-I', str(SOURCE_DIR), '-o', str(library),
               str(c_file), '-lm']
    logger.info('compiling %s: %s', what, ' '.join(command))
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        raise RuntimeError(f'compiling {what} failed (exit {result.returncode}):\n'
                           f'{" ".join(command)}\n{result.stderr.strip()}')
    warnings = result.stderr.strip()
    if warnings:
        logger.warning('compiler warnings for %s:\n%s', what, warnings)
    return warnings


def pack_fmu(target: pathlib.Path, description: str, library: pathlib.Path,
             sources: Sequence[pathlib.Path] = ()) -> pathlib.Path:
    """
    Write the FMU archive ``target`` (it appears atomically: written beside it, then renamed).

    It holds ``modelDescription.xml`` (the text ``description``), the shared library
    under ``binaries/<platform>/`` and ``sources`` under ``sources/``. Every entry is dated
    2020-01-01, so that the same inputs give the same bytes (one folder in the extraction
    cache).
    """
    platform_dir, _ = platform()
    entries = [('modelDescription.xml', description.encode('utf-8')),
               (f'binaries/{platform_dir}/{library.name}', library.read_bytes()),
               *((f'sources/{path.name}', path.read_bytes()) for path in sources)]
    staged = target.parent / f'.{target.name}.{os.getpid()}.tmp'
    with zipfile.ZipFile(staged, 'w', compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in entries:
            archive.writestr(zipfile.ZipInfo(name, date_time=(2020, 1, 1, 0, 0, 0)), data,
                             compress_type=zipfile.ZIP_DEFLATED)
    os.replace(staged, target)
    return target


def build_fmu(name: str, out_dir: str | os.PathLike) -> pathlib.Path:
    """
    Compile the FMU ``name`` and write ``out_dir/<modelIdentifier>.fmu``.

    The archive holds ``modelDescription.xml``,
    ``binaries/<platform>/<modelIdentifier>.so`` and ``sources/`` (the C file,
    ``fmi2_model.h`` and the FMI headers). The file appears atomically (written to a temporary
    name, then renamed), so concurrent builders do not see half-written FMUs.

    Parameters
    ----------
    name : str
        A key of :data:`~mshoot_core.fmu_cache.MODELS` (``'r1c1'`` or ``'r2c2'``).
    out_dir : path
        Target directory, created if missing.

    Returns
    -------
    pathlib.Path
        Path of the written ``.fmu``.

    Raises
    ------
    ValueError
        For an unknown model name.
    RuntimeError
        If the compiler is missing or the compilation fails.

    """
    source = model_source(name)
    _, suffix = platform()
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    guid = _guid(name)
    target = out_dir / f'{source.model_identifier}.fmu'
    with tempfile.TemporaryDirectory(prefix='mshoot-fmu-') as tmp:
        library = pathlib.Path(tmp) / f'{source.model_identifier}{suffix}'
        compile_library(SOURCE_DIR / source.c_file, library, f'the {name} FMU',
                        [f'-DMODEL_GUID="{guid}"'])
        stamp = datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ')
        description = (SOURCE_DIR / source.description_template).read_text(encoding='utf-8')
        description = description.replace('@GUID@', guid).replace('@DATETIME@', stamp)
        pack_fmu(target, description, library,
                 [path for path in source.files() if path.suffix in ('.c', '.h')])
    logger.info('built %s', target)
    return target


def ensure_fmu(name: str) -> pathlib.Path:
    """
    Return the FMU ``name`` from the cache, building it first if it is not there.

    For setup and tests; the runtime uses :func:`mshoot_core.fmu_cache.find_fmu`,
    which never builds.

    Parameters
    ----------
    name : str
        A key of :data:`~mshoot_core.fmu_cache.MODELS`.

    Returns
    -------
    pathlib.Path
        ``<cache>/<source hash>/<modelIdentifier>.fmu``.

    Raises
    ------
    ValueError
        For an unknown model name.
    RuntimeError
        If the compiler is missing or the compilation fails.

    """
    path = cached_fmu_file(name)
    if not path.is_file():
        logger.info('no cached %s FMU for these sources, building %s', name, path)
        build_fmu(name, path.parent)
    return path


def build_driver(name: str, target: str | os.PathLike) -> pathlib.Path:
    """
    Compile the batch driver ``name`` (``'cs'`` or ``'me'``) into the file ``target``.

    The library appears atomically (compiled to a temporary name, then renamed).

    Raises
    ------
    ValueError
        For an unknown driver name.
    RuntimeError
        If the compiler is missing or the compilation fails.

    """
    source = driver_source(name)
    target = pathlib.Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    staged = target.parent / f'.{target.name}.{os.getpid()}.tmp'
    try:
        compile_library(SOURCE_DIR / source.c_file, staged, f'the {source.description}')
    except RuntimeError:
        staged.unlink(missing_ok=True)
        raise
    os.replace(staged, target)
    logger.info('built %s', target)
    return target


def ensure_driver(name: str) -> pathlib.Path:
    """
    Return the batch driver ``name`` from the cache, building it first if it is not there.

    For setup and tests; the runtime uses
    :func:`mshoot_core.fmu_cache.find_driver`, which never builds.

    Raises
    ------
    ValueError
        For an unknown driver name.
    RuntimeError
        If the compiler is missing or the compilation fails.

    """
    path = cached_driver_file(name)
    if not path.is_file():
        build_driver(name, path)
    return path


def ensure_cache(models: list[str] | tuple[str, ...] = ('r1c1',)) -> list[pathlib.Path]:
    """
    Build what the runtime needs into the cache: the FMUs ``models`` and every driver.

    What is already built for the current sources is kept. Returns the paths
    (FMUs first, then the drivers).

    Raises
    ------
    ValueError
        For an unknown model name.
    RuntimeError
        If the compiler is missing or a compilation fails.

    """
    return [*(ensure_fmu(name) for name in models), *(ensure_driver(name) for name in DRIVERS)]


def main(argv: list[str] | None = None) -> int:
    """Command line: build FMUs into a directory or into the cache; print their paths."""
    parser = argparse.ArgumentParser(prog='python -m mshoot_core.fmu_build',
                                     description='Build the mshoot FMUs and batch drivers '
                                                 'with gcc.')
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument('--out', type=pathlib.Path, help='directory to write the .fmu files to')
    where.add_argument('--cache', action='store_true',
                       help=f'build into the cache (${CACHE_ENV} or ~/.cache/mshoot/fmu), '
                            'where the runtime finds them, the FMUs and the batched '
                            'Co-Simulation and Model Exchange drivers; what is already built '
                            'for these sources is kept')
    parser.add_argument('models', nargs='*', metavar='MODEL',
                        help=f'FMUs to build, from {sorted(MODELS)} (default: r1c1)')
    args = parser.parse_args(argv)
    models = args.models or ['r1c1']
    unknown = [name for name in models if name not in MODELS]
    if unknown:
        parser.error(f'unknown FMUs {unknown}: expected names from {sorted(MODELS)}')
    logging.basicConfig(level=logging.INFO, format='[fmu_build] %(message)s', stream=sys.stderr)
    try:
        if args.cache:
            paths = ensure_cache(models)
        else:
            paths = [build_fmu(name, args.out) for name in models]
    except (ValueError, RuntimeError) as error:
        logger.error('%s', error)
        return 1
    sys.stdout.write(''.join(f'{path}\n' for path in paths))
    return 0


if __name__ == '__main__':
    sys.exit(main())
