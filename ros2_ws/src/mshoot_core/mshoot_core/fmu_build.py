"""Build the project's FMI 2.0 FMUs from the C sources in ``fmu_src/`` with gcc.

Two models ship as C sources:

- ``r1c1``: the R1C1 zone of the OU44 reference case (Model Exchange and
  Co-Simulation in one binary, FMU state get/set/serialise, directional
  derivatives; ``fmi2DoStep`` is the exact per-step solution);
- ``r2c2``: a two-node air + wall zone written in another style (Model
  Exchange only, no FMU state), used by the tests to show that any FMI 2.0 FMU
  works through :class:`mshoot_core.models.fmi.FmiModel`.

:func:`fmu_path` returns a cached build, compiled on first use into
``$MSHOOT_FMU_DIR/<hash>/`` (default ``~/.cache/mshoot/fmu/<hash>/``) where
``<hash>`` covers the model's sources, the FMI headers and this builder, so an
edited source is rebuilt and an unchanged one never is. This module needs only
the standard library and a C compiler (``$CC``, default ``gcc``).

Command line::

    python -m mshoot_core.fmu_build --out DIR [MODEL ...]   # build into DIR
    python -m mshoot_core.fmu_build --cache [MODEL ...]     # build into the cache if missing
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import hashlib
import logging
import os
import pathlib
import shutil
import struct
import subprocess
import sys
import tempfile
import uuid
import zipfile

logger = logging.getLogger(__name__)

#: Directory of the C sources, modelDescription templates and FMI 2.0 headers.
SOURCE_DIR = pathlib.Path(__file__).resolve().parent / 'fmu_src'
#: The standard FMI 2.0 headers (2-clause BSD, Modelica Association), as shipped by fmpy.
FMI2_HEADERS = ('fmi2Functions.h', 'fmi2FunctionTypes.h', 'fmi2TypesPlatform.h')
#: Compiler flags; -fvisibility=hidden leaves only the FMI functions exported.
CFLAGS = ('-shared', '-fPIC', '-O2', '-std=c99', '-Wall', '-fvisibility=hidden')
#: Environment variable naming the cache base directory.
CACHE_ENV = 'MSHOOT_FMU_DIR'


@dataclasses.dataclass(frozen=True)
class FmuSource:
    """One FMU's sources in :data:`SOURCE_DIR`.

    Attributes
    ----------
    model_identifier : str
        The FMI modelIdentifier: the shared library's and the FMU file's stem.
    c_file : str
        The single C source file.
    description_template : str
        The modelDescription.xml template (``@GUID@`` and ``@DATETIME@`` are
        filled in by the builder).
    """

    model_identifier: str
    c_file: str
    description_template: str

    def files(self) -> list[pathlib.Path]:
        """Every file the build depends on (sources, template, headers)."""
        names = [self.c_file, self.description_template, *FMI2_HEADERS]
        return [SOURCE_DIR / name for name in names]


#: The FMUs this module can build, by name.
MODELS: dict[str, FmuSource] = {
    'r1c1': FmuSource('R1C1', 'r1c1.c', 'r1c1.xml'),
    'r2c2': FmuSource('R2C2', 'r2c2.c', 'r2c2.xml'),
}


def _model(name: str) -> FmuSource:
    if name not in MODELS:
        raise ValueError(f'unknown FMU {name!r}: expected one of {sorted(MODELS)}')
    return MODELS[name]


def _platform() -> tuple[str, str]:
    """Return the FMI 2.0 binaries folder and the shared-library suffix of this host."""
    if struct.calcsize('P') != 8:
        raise RuntimeError('building FMUs needs a 64-bit Python/host')
    if sys.platform.startswith('linux'):
        return 'linux64', '.so'
    if sys.platform == 'darwin':
        return 'darwin64', '.dylib'
    raise RuntimeError(f'building FMUs with gcc is supported on Linux and macOS, '
                       f'not on {sys.platform}')


def source_hash(name: str) -> str:
    """Hash of everything the build of ``name`` depends on (16 hex digits).

    Covers the model's C file and template, the FMI headers, this builder
    and the compiler flags.
    """
    digest = hashlib.sha256()
    for path in [*_model(name).files(), pathlib.Path(__file__).resolve()]:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    digest.update(' '.join(CFLAGS).encode())
    return digest.hexdigest()[:16]


def _guid(name: str) -> str:
    """Return a GUID derived from the sources: the same sources give the same GUID."""
    token = f'mshoot-fmu:{name}:{source_hash(name)}'
    return '{' + str(uuid.uuid5(uuid.NAMESPACE_URL, token)) + '}'


def find_compiler() -> str:
    """Return the C compiler to use (``$CC`` or ``gcc``).

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


def build_fmu(name: str, out_dir: str | os.PathLike) -> pathlib.Path:
    """Compile the FMU ``name`` and write ``out_dir/<modelIdentifier>.fmu``.

    The archive holds ``modelDescription.xml``,
    ``binaries/<platform>/<modelIdentifier>.so`` and ``sources/`` (the C file
    and the FMI headers). The file appears atomically (written to a temporary
    name, then renamed), so concurrent builders do not see half-written FMUs.

    Parameters
    ----------
    name : str
        A key of :data:`MODELS` (``'r1c1'`` or ``'r2c2'``).
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
    source = _model(name)
    compiler = find_compiler()
    platform_dir, suffix = _platform()
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    guid = _guid(name)
    target = out_dir / f'{source.model_identifier}.fmu'
    with tempfile.TemporaryDirectory(prefix='mshoot-fmu-') as tmp:
        library = pathlib.Path(tmp) / f'{source.model_identifier}{suffix}'
        command = [compiler, *CFLAGS, f'-DMODEL_GUID="{guid}"', '-I', str(SOURCE_DIR),
                   '-o', str(library), str(SOURCE_DIR / source.c_file), '-lm']
        logger.info('compiling %s: %s', name, ' '.join(command))
        result = subprocess.run(command, capture_output=True, text=True, check=False)
        if result.returncode != 0:
            raise RuntimeError(f'compiling the {name} FMU failed (exit {result.returncode}):\n'
                               f'{" ".join(command)}\n{result.stderr.strip()}')
        if result.stderr.strip():
            logger.warning('compiler warnings for %s:\n%s', name, result.stderr.strip())
        stamp = datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ')
        description = (SOURCE_DIR / source.description_template).read_text(encoding='utf-8')
        description = description.replace('@GUID@', guid).replace('@DATETIME@', stamp)
        partial = pathlib.Path(tmp) / target.name
        with zipfile.ZipFile(partial, 'w', compression=zipfile.ZIP_DEFLATED) as archive:
            archive.writestr('modelDescription.xml', description)
            archive.write(library, f'binaries/{platform_dir}/{library.name}')
            for path in source.files():
                if path.suffix in ('.c', '.h'):
                    archive.write(path, f'sources/{path.name}')
        # Same filesystem as the target for an atomic rename.
        staged = out_dir / f'.{target.name}.{os.getpid()}.tmp'
        shutil.copyfile(partial, staged)
        os.replace(staged, target)
    logger.info('built %s', target)
    return target


def fmu_cache_dir() -> pathlib.Path:
    """Return the FMU cache's base directory: ``$MSHOOT_FMU_DIR`` or ``~/.cache/mshoot/fmu``."""
    base = os.environ.get(CACHE_ENV)
    if base:
        return pathlib.Path(base).expanduser()
    return pathlib.Path.home() / '.cache' / 'mshoot' / 'fmu'


def cached_fmu_file(name: str) -> pathlib.Path:
    """Where the cached build of ``name`` lives (whether or not it exists yet)."""
    source = _model(name)
    return fmu_cache_dir() / source_hash(name) / f'{source.model_identifier}.fmu'


def fmu_path(name: str) -> pathlib.Path:
    """Return the cached FMU ``name``, building it with gcc on first use.

    Parameters
    ----------
    name : str
        A key of :data:`MODELS`.

    Returns
    -------
    pathlib.Path
        ``<cache>/<source hash>/<modelIdentifier>.fmu``.
    """
    path = cached_fmu_file(name)
    if not path.is_file():
        logger.info('no cached %s FMU for these sources, building %s', name, path)
        build_fmu(name, path.parent)
    return path


#: C source of the batched Co-Simulation driver (see :mod:`mshoot_core.models.fmi`).
CS_BATCH_SOURCE = SOURCE_DIR / 'cs_batch.c'
#: C source of the batched Model Exchange driver (explicit Runge-Kutta, see
#: :mod:`mshoot_core.models.fmi`).
ME_BATCH_SOURCE = SOURCE_DIR / 'me_batch.c'


def _driver_library(source: pathlib.Path, stem: str) -> pathlib.Path | None:
    """Return the compiled driver ``source`` (cached by content hash), building it if missing.

    Returns None (with a warning) when no compiler is available or the
    compilation fails: FMUs then run through fmpy's calls, slower but the same.
    """
    digest = hashlib.sha256(source.read_bytes())
    for header in sorted(SOURCE_DIR.glob('fmi2*.h')):
        digest.update(header.read_bytes())
    digest.update(' '.join(CFLAGS).encode())
    _, suffix = _platform()
    target = fmu_cache_dir() / 'driver' / digest.hexdigest()[:16] / f'{stem}{suffix}'
    if target.is_file():
        return target
    try:
        compiler = find_compiler()
    except RuntimeError as exc:
        logger.warning('no batched FMU driver: %s', exc)
        return None
    target.parent.mkdir(parents=True, exist_ok=True)
    staged = target.parent / f'.{target.name}.{os.getpid()}.tmp'
    command = [compiler, *CFLAGS, '-I', str(SOURCE_DIR), '-o', str(staged), str(source), '-lm']
    logger.info('compiling the batched FMU driver %s: %s', stem, ' '.join(command))
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        logger.warning('compiling the batched FMU driver %s failed, using fmpy calls:\n%s',
                       stem, result.stderr.strip())
        return None
    os.replace(staged, target)
    return target


def cs_batch_library() -> pathlib.Path | None:
    """Return the compiled batched Co-Simulation driver, building it on first use.

    Returns None (with a warning) when no compiler is available: FMUs then run
    through fmpy's calls interval by interval, slower but the same.
    """
    return _driver_library(CS_BATCH_SOURCE, 'mshoot_cs_batch')


def me_batch_library() -> pathlib.Path | None:
    """Return the compiled batched Model Exchange driver, building it on first use.

    Returns None (with a warning) when no compiler is available: Model
    Exchange FMUs then integrate with fmpy's CVode, slower and the same up to
    the integrator tolerance.
    """
    return _driver_library(ME_BATCH_SOURCE, 'mshoot_me_batch')


def r1c1_fmu_path() -> pathlib.Path:
    """Return the cached R1C1 FMU (ME + CS), building it on first use."""
    return fmu_path('r1c1')


def main(argv: list[str] | None = None) -> int:
    """Command line: build FMUs into a directory or into the cache; print their paths."""
    parser = argparse.ArgumentParser(prog='python -m mshoot_core.fmu_build',
                                     description='Build the mshoot FMUs with gcc.')
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument('--out', type=pathlib.Path, help='directory to write the .fmu files to')
    where.add_argument('--cache', action='store_true',
                       help=f'build into the cache (${CACHE_ENV} or ~/.cache/mshoot/fmu) '
                            'unless already there, with the batched Co-Simulation and Model '
                            'Exchange drivers')
    parser.add_argument('models', nargs='*', metavar='MODEL', default=['r1c1'],
                        help=f'models to build, from {sorted(MODELS)} (default: r1c1)')
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format='[fmu_build] %(message)s', stream=sys.stderr)
    try:
        for name in args.models:
            path = fmu_path(name) if args.cache else build_fmu(name, args.out)
            sys.stdout.write(f'{path}\n')
        if args.cache:
            for driver in (cs_batch_library(), me_batch_library()):
                if driver is not None:
                    sys.stdout.write(f'{driver}\n')
    except (ValueError, RuntimeError) as error:
        logger.error('%s', error)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
