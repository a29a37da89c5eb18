"""
Where the project's built FMUs and batch drivers live, and how the runtime finds them.

``make setup`` (``python -m mshoot_core.fmu_build --cache``, see
:mod:`mshoot_core.fmu_build`) compiles the C sources in ``fmu_src/`` into the
cache ``$MSHOOT_FMU_DIR`` (default ``~/.cache/mshoot/fmu``):

- ``<cache>/<hash>/<modelIdentifier>.fmu``: the FMUs of :data:`MODELS`;
- ``<cache>/driver/<hash>/<library>.so``: the batch drivers of :data:`DRIVERS`,

where ``<hash>`` covers everything the build reads (the C file, the FMI
headers, the template, the builder), so edited sources live under a new hash
and are never mistaken for an old build. The runtime only *finds* builds here
(:func:`find_fmu`, :func:`find_driver`): it never compiles, and a missing
build is a :class:`NotBuiltError` naming the file and the command that builds
it.

Any FMU a model loads is extracted once, into
``<cache>/extracted/<sha256 of the .fmu file>/`` (:func:`extract_fmu`): the
next model of the same file (also in another process) uses that folder. An
extraction is staged in a folder next to it and renamed into place when
complete, so a failing or concurrent extraction never leaves a half-written
folder nor a temporary one behind. This module needs only the standard library.
"""
from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import pathlib
import shutil
import struct
import sys
import tempfile
from typing import Callable
import zipfile

logger = logging.getLogger(__name__)

#: Directory of the C sources, modelDescription templates and FMI 2.0 headers.
SOURCE_DIR = pathlib.Path(__file__).resolve().parent / 'fmu_src'
#: The standard FMI 2.0 headers (2-clause BSD, Modelica Association), as shipped by fmpy.
FMI2_HEADERS = ('fmi2Functions.h', 'fmi2FunctionTypes.h', 'fmi2TypesPlatform.h')
#: The FMI 2.0 functions every model's C file shares (it includes this header once).
MODEL_HEADER = 'fmi2_model.h'
#: The builder (its compiler flags and archive layout are part of every build).
BUILDER = pathlib.Path(__file__).resolve().parent / 'fmu_build.py'
#: Environment variable naming the cache base directory.
CACHE_ENV = 'MSHOOT_FMU_DIR'
#: The command that fills the cache (with FMU names: those FMUs too); ``make setup`` runs it.
BUILD_COMMAND = 'python -m mshoot_core.fmu_build --cache'
#: Sub-folder of the cache holding extracted FMUs, one folder per FMU file hash.
EXTRACTED = 'extracted'
#: Prefix of the staging folders of extractions in progress (inside :data:`EXTRACTED`).
STAGING_PREFIX = '.staging-'


@dataclasses.dataclass(frozen=True)
class FmuSource:
    """
    One FMU's sources in :data:`SOURCE_DIR`.

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
        """Every source file the build depends on (C file, template, headers)."""
        names = [self.c_file, self.description_template, MODEL_HEADER, *FMI2_HEADERS]
        return [SOURCE_DIR / name for name in names]


@dataclasses.dataclass(frozen=True)
class DriverSource:
    """
    One batch driver's source in :data:`SOURCE_DIR`.

    Attributes
    ----------
    library : str
        Stem of the shared library (and of its entry point ``<library>``).
    c_file : str
        The single C source file.
    description : str
        What the driver is, for messages.

    """

    library: str
    c_file: str
    description: str

    def files(self) -> list[pathlib.Path]:
        """Every source file the build depends on (C file, headers)."""
        return [SOURCE_DIR / name for name in (self.c_file, *FMI2_HEADERS)]


#: The FMUs built from :data:`SOURCE_DIR`, by name: ``r1c1`` is the runtime's built-in
#: zone (``make setup`` builds it), ``r2c2`` a second FMU the tests build themselves,
#: ``setpoint_zone`` a zone whose air state is an energy, heated by a local loop on a
#: setpoint with an override (the plant of ``cards/setpoint_zone_plant.yaml``).
MODELS: dict[str, FmuSource] = {
    'r1c1': FmuSource('R1C1', 'r1c1.c', 'r1c1.xml'),
    'r2c2': FmuSource('R2C2', 'r2c2.c', 'r2c2.xml'),
    'setpoint_zone': FmuSource('SetpointZone', 'setpoint_zone.c', 'setpoint_zone.xml'),
}
#: The batch drivers (:mod:`mshoot_core.models.fmi_drivers`), by name.
DRIVERS: dict[str, DriverSource] = {
    'cs': DriverSource('mshoot_cs_batch', 'cs_batch.c', 'batched Co-Simulation driver'),
    'me': DriverSource('mshoot_me_batch', 'me_batch.c', 'batched Model Exchange driver'),
}


class NotBuiltError(FileNotFoundError):
    """A build product (an FMU or a batch driver) is missing from the cache."""


def model_source(name: str) -> FmuSource:
    """
    Return the sources of the FMU ``name`` (a key of :data:`MODELS`).

    Raises
    ------
    ValueError
        For an unknown name.

    """
    if name not in MODELS:
        raise ValueError(f'unknown FMU {name!r}: expected one of {sorted(MODELS)}')
    return MODELS[name]


def driver_source(name: str) -> DriverSource:
    """
    Return the source of the batch driver ``name`` (a key of :data:`DRIVERS`).

    Raises
    ------
    ValueError
        For an unknown name.

    """
    if name not in DRIVERS:
        raise ValueError(f'unknown batch driver {name!r}: expected one of {sorted(DRIVERS)}')
    return DRIVERS[name]


def platform() -> tuple[str, str]:
    """
    Return the FMI 2.0 binaries folder and the shared-library suffix of this host.

    Raises
    ------
    RuntimeError
        On a 32-bit Python or a platform other than Linux and macOS.

    """
    if struct.calcsize('P') != 8:
        raise RuntimeError('the mshoot FMUs need a 64-bit Python/host')
    if sys.platform.startswith('linux'):
        return 'linux64', '.so'
    if sys.platform == 'darwin':
        return 'darwin64', '.dylib'
    raise RuntimeError(f'the mshoot FMUs are built with gcc on Linux and macOS, '
                       f'not on {sys.platform}')


def _hash(files: list[pathlib.Path]) -> str:
    digest = hashlib.sha256()
    for path in [*files, BUILDER]:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def source_hash(name: str) -> str:
    """
    Hash of everything the build of the FMU ``name`` depends on (16 hex digits).

    Covers the model's C file and template, the FMI headers and the builder
    (its compiler flags).
    """
    return _hash(model_source(name).files())


def driver_hash(name: str) -> str:
    """Hash of everything the build of the batch driver ``name`` depends on (16 hex digits)."""
    return _hash(driver_source(name).files())


def cache_dir() -> pathlib.Path:
    """Return the cache's base directory: ``$MSHOOT_FMU_DIR`` or ``~/.cache/mshoot/fmu``."""
    base = os.environ.get(CACHE_ENV)
    if base:
        return pathlib.Path(base).expanduser()
    return pathlib.Path.home() / '.cache' / 'mshoot' / 'fmu'


def cached_fmu_file(name: str) -> pathlib.Path:
    """Where the build of the FMU ``name`` lives (whether or not it exists)."""
    source = model_source(name)
    return cache_dir() / source_hash(name) / f'{source.model_identifier}.fmu'


def cached_driver_file(name: str) -> pathlib.Path:
    """Where the build of the batch driver ``name`` lives (whether or not it exists)."""
    _, suffix = platform()
    return cache_dir() / 'driver' / driver_hash(name) / f'{driver_source(name).library}{suffix}'


def _missing(what: str, path: pathlib.Path, command: str) -> NotBuiltError:
    """Return the error for a missing build, with the command that builds it."""
    others = sorted(str(p) for p in path.parent.parent.glob(f'*/{path.name}'))
    stale = (f'; the cache holds it only for other sources ({", ".join(others)}): the '
             f'sources changed since the last build') if others else ''
    where = f'${CACHE_ENV}={os.environ[CACHE_ENV]}' if os.environ.get(CACHE_ENV) \
        else f'${CACHE_ENV} unset'
    return NotBuiltError(f'{what} is not built: expected {path} ({where}){stale}. '
                         f'Build it with `make setup` or `{command}`')


def find_fmu(name: str) -> pathlib.Path:
    """
    Return the built FMU ``name`` from the cache; never builds.

    Parameters
    ----------
    name : str
        A key of :data:`MODELS`.

    Returns
    -------
    pathlib.Path
        ``<cache>/<source hash>/<modelIdentifier>.fmu``.

    Raises
    ------
    NotBuiltError
        If the FMU is not built for the current sources (the message says
        where it was expected and which command builds it).
    ValueError
        For an unknown name.

    """
    path = cached_fmu_file(name)
    if not path.is_file():
        raise _missing(f'the {model_source(name).model_identifier} FMU', path,
                       f'{BUILD_COMMAND} {name}')
    return path


def find_driver(name: str) -> pathlib.Path:
    """
    Return the built batch driver ``name`` (``'cs'`` or ``'me'``) from the cache; never builds.

    Raises
    ------
    NotBuiltError
        If the driver is not built for the current sources.
    ValueError
        For an unknown name.

    """
    path = cached_driver_file(name)
    if not path.is_file():
        source = driver_source(name)
        raise _missing(f'the {source.description} ({source.library}, from '
                       f'fmu_src/{source.c_file})', path, BUILD_COMMAND)
    return path


def file_sha256(path: str | os.PathLike) -> str:
    """Return the sha256 of a file's bytes (64 hex digits)."""
    digest = hashlib.sha256()
    with open(path, 'rb') as stream:
        for block in iter(lambda: stream.read(1 << 20), b''):
            digest.update(block)
    return digest.hexdigest()


def extracted_dir(fmu_file: str | os.PathLike) -> pathlib.Path:
    """Where the FMU file ``fmu_file`` is (or would be) extracted: keyed by its sha256."""
    return cache_dir() / EXTRACTED / file_sha256(fmu_file)[:32]


def _safe_members(archive: zipfile.ZipFile, label: str) -> list[str]:
    """Return the archive's member names, refusing any that would land outside the target."""
    names = archive.namelist()
    for name in names:
        parts = name.split('/')
        if '\\' in name or ':' in name or name.startswith('/') or '..' in parts:
            raise ValueError(f'{label}: illegal path {name!r} in the archive (an FMU holds '
                             'relative paths with forward slashes only)')
    return names


def extract_fmu(fmu_file: str | os.PathLike,
                check: Callable[[pathlib.Path], None] | None = None) -> pathlib.Path:
    """
    Extract ``fmu_file`` into the cache once; return its folder.

    The folder is ``<cache>/extracted/<sha256>``; an existing one is reused
    as is. A new extraction goes to a staging folder beside it, is checked
    with ``check(folder)`` (e.g. reading its modelDescription) and renamed
    into place; on any failure the staging folder is removed, so nothing is
    left behind.

    Parameters
    ----------
    fmu_file : path
        The ``.fmu`` file.
    check : callable, optional
        Called with the staged folder; raising rejects the extraction.

    Raises
    ------
    FileNotFoundError
        If ``fmu_file`` does not exist.
    ValueError
        If the file is not a ZIP archive or holds illegal paths (and whatever
        ``check`` raises).

    """
    path = pathlib.Path(fmu_file)
    if not path.is_file():
        raise FileNotFoundError(f'FMU not found: {path}')
    target = extracted_dir(path)
    if target.is_dir():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = pathlib.Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=target.parent))
    try:
        try:
            with zipfile.ZipFile(path) as archive:
                archive.extractall(staging, members=_safe_members(archive, str(path)))
        except zipfile.BadZipFile as error:
            raise ValueError(f'{path} is not an FMU: not a ZIP archive ({error})') from error
        if check is not None:
            check(staging)
        try:
            os.rename(staging, target)
        except OSError:
            if not target.is_dir():  # not a concurrent extraction of the same file
                raise
            shutil.rmtree(staging, ignore_errors=True)  # another process was first
        else:
            logger.debug('extracted %s into %s', path, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return target
