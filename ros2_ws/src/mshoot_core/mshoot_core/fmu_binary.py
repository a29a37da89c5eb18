"""
An FMU's shared library: loaded once in a child process before this process loads it.

A damaged binary (a truncated ``binaries/linux64/<id>.so``) kills the process that maps it
with a signal (a bus error), and a binary that needs a library the host lacks fails deep in
fmpy. :func:`check_binary` loads the binary in a child Python process first, with every
library this process preloaded, and turns what happens there into one
:class:`FmuBinaryError` (a ValueError): the library it lacks (by name, with how to provide
it), the signal that killed the child, or the loader's message. A binary that loaded is
remembered in the FMU cache (:func:`mshoot_core.fmu_cache.cache_dir`, ``checked/``), keyed
by the binary's sha256 and the preloaded libraries, so a later run costs one hash.

Libraries to preload (:class:`Library`, a card's ``preload`` list): a path to a shared
library, a name the dynamic linker finds (``libgomp.so.1``), or the source of a stand-in
(a folder with one C file and an optional linker version script, ``*.map``) that is built
with gcc into the cache (``<cache>/stand-in/<hash>/<soname>``) for the ``soname`` given, or,
without one, for the library the binary is found to lack. Preloaded libraries are loaded
``RTLD_GLOBAL`` into this process (:func:`preload`), so the FMU's binary finds their symbols.
The standard library only.
"""
from __future__ import annotations

import _ctypes
import contextlib
import ctypes
import dataclasses
import hashlib
import json
import logging
import os
import pathlib
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from typing import Iterator, Sequence
from xml.etree import ElementTree

from mshoot_core import fmu_cache

logger = logging.getLogger(__name__)

#: Sub-folder of the cache holding the binaries that loaded (one file per check key).
CHECKED = 'checked'
#: Sub-folder of the cache holding the stand-in libraries built from sources.
STAND_IN = 'stand-in'
#: Seconds a child process may take to load a binary.
LOAD_TIMEOUT_S = 60.0
#: Exit code of the child when the loader refused the binary (its message on stderr).
_REFUSED = 3
#: What the child runs: preload ``argv[2:]`` (RTLD_GLOBAL), then load ``argv[1]`` and find the
#: FMI 2.0 entry points. Each file is announced on stdout before it is loaded, so a signal
#: names the file that raised it.
_CHILD = r"""
import ctypes, sys
for path in [*sys.argv[2:], sys.argv[1]]:
    sys.stdout.write(path + '\n'); sys.stdout.flush()
    try:
        lib = ctypes.CDLL(path, mode=ctypes.RTLD_GLOBAL if path != sys.argv[1] else 0)
    except OSError as error:
        sys.stderr.write(str(error)); sys.exit(3)
missing = [name for name in ('fmi2GetVersion', 'fmi2Instantiate', 'fmi2FreeInstance')
           if not hasattr(lib, name)]
if missing:
    sys.stderr.write('no FMI 2.0 entry points ' + ', '.join(missing)); sys.exit(3)
"""
_MISSING = re.compile(r'(\S+?): cannot open shared object file')
_VERSION = re.compile(r"version `([^']+)' not found \(required by [^)]*\)")

_lock = threading.Lock()
#: Libraries preloaded into this process, in order (absolute paths or sonames).
_PRELOADED: dict[str, ctypes.CDLL] = {}


class FmuBinaryError(ValueError):
    """
    An FMU's binary does not load: ``missing`` names the library it lacks, if that is why.

    The message is one line.
    """

    def __init__(self, message: str, missing: str | None = None) -> None:
        super().__init__(message)
        self.missing = missing


@dataclasses.dataclass(frozen=True)
class Library:
    """
    A library to preload before an FMU's binary.

    Attributes
    ----------
    path : str or None
        A shared library file (absolute), or a name the dynamic linker finds.
    source : pathlib.Path or None
        A folder with the source of a stand-in: one ``*.c`` file and optionally one ``*.map``
        linker version script.
    soname : str or None
        The stand-in's name (``libgfortran.so.3``); None: the library the binary lacks.

    """

    path: str | None = None
    source: pathlib.Path | None = None
    soname: str | None = None

    def __post_init__(self) -> None:
        if (self.path is None) == (self.source is None):
            raise ValueError(f'a library is a path or a stand-in source, got {self!r}')

    def label(self) -> str:
        """Return the library as a card names it."""
        if self.path is not None:
            return self.path
        return f'the stand-in {self.soname or "(any library)"} from {self.source}'


def binary_file(folder: str | os.PathLike, model_identifier: str) -> pathlib.Path:
    """Return the binary of an extracted FMU on this host: ``binaries/<platform>/<id><suffix>``."""
    platform, suffix = fmu_cache.platform()
    return pathlib.Path(folder) / 'binaries' / platform / f'{model_identifier}{suffix}'


def model_identifiers(folder: str | os.PathLike) -> tuple[str, ...]:
    """
    Return the modelIdentifiers of an extracted FMU (Model Exchange first), from its XML.

    Reads only the head of ``modelDescription.xml`` (the interface elements precede the
    variables), so it costs nothing even for an FMU of thousands of variables.
    """
    path = pathlib.Path(folder) / 'modelDescription.xml'
    found: dict[str, str] = {}
    try:
        for _, element in ElementTree.iterparse(path, events=('start',)):
            if element.tag in ('ModelExchange', 'CoSimulation'):
                found[element.tag] = element.get('modelIdentifier', '')
            elif element.tag in ('ModelVariables', 'UnitDefinitions', 'TypeDefinitions'):
                break
    except (OSError, ElementTree.ParseError) as error:
        raise FmuBinaryError(f'{path}: cannot read the modelIdentifier ({error})') from None
    return tuple(found[tag] for tag in ('ModelExchange', 'CoSimulation')
                 if found.get(tag))


@contextlib.contextmanager
def isolated(binary: str | os.PathLike) -> Iterator[pathlib.Path]:
    """
    Hold an FMU's binary loaded with ``RTLD_DEEPBIND`` while fmpy loads the same path.

    The dynamic loader keeps the binding of an object's first load, so fmpy's load inside
    the ``with`` block gets it: the binary's own symbols before those of the global scope.
    An FMU that carries its own BLAS/LAPACK (``dgesv_``, ``dgemm_``, ...) then calls its own
    copy, not that of a library loaded ``RTLD_GLOBAL`` before it (CasADi's OpenBLAS, with
    ``MSHOOT_IPOPT_BUILD=casadi``): its results do not depend on what else the process
    loaded. What the binary does not define still comes from the global scope (the
    preloaded libraries, :func:`preload`). This handle is closed on exit, so fmpy's is the
    only one left (freeing the FMU unloads the binary as before). Yields the binary's path.
    Without ``RTLD_DEEPBIND`` (not glibc) it only yields the path.
    """
    path = pathlib.Path(binary).resolve()
    deepbind = getattr(os, 'RTLD_DEEPBIND', 0)
    if not deepbind:
        yield path
        return
    library = ctypes.CDLL(str(path), mode=os.RTLD_NOW | deepbind)
    try:
        yield path
    finally:
        _ctypes.dlclose(library._handle)  # (a CDLL has no close)


def preloaded() -> tuple[str, ...]:
    """Return the libraries preloaded into this process (paths or names), in order."""
    with _lock:
        return tuple(_PRELOADED)


def preload(libraries: Sequence[str]) -> None:
    """
    Load ``libraries`` (paths or names) ``RTLD_GLOBAL`` into this process, once each.

    Check them first in a child (:func:`check_binary` does) when they may be damaged.

    Raises
    ------
    FmuBinaryError
        If one does not load.

    """
    with _lock:
        for library in libraries:
            if library in _PRELOADED:
                continue
            try:
                _PRELOADED[library] = ctypes.CDLL(library, mode=ctypes.RTLD_GLOBAL)
            except OSError as error:
                raise FmuBinaryError(f'cannot preload {library}: {error}') from error
            logger.info('preloaded %s', library)


def _sources(folder: pathlib.Path) -> tuple[pathlib.Path, pathlib.Path | None]:
    """Return the C file and the version script (or None) of a stand-in's source folder."""
    if not folder.is_dir():
        raise FmuBinaryError(f'stand-in source folder not found: {folder}')
    c_files = sorted(folder.glob('*.c'))
    maps = sorted(folder.glob('*.map'))
    if len(c_files) != 1 or len(maps) > 1:
        raise FmuBinaryError(f'{folder}: a stand-in source folder holds one C file and at most '
                             f'one version script (*.map), got {[p.name for p in c_files]} and '
                             f'{[p.name for p in maps]}')
    return c_files[0], (maps[0] if maps else None)


def stand_in(source: str | os.PathLike, soname: str) -> pathlib.Path:
    """
    Build the stand-in library ``soname`` from ``source`` into the cache (once); its path.

    The build is staged in a temporary folder and renamed into place, so concurrent processes
    never see a half-written library; its folder is keyed by the sources and the name.

    Raises
    ------
    FmuBinaryError
        If the folder does not hold one C file (and at most one ``*.map``), or gcc fails.

    """
    if not re.fullmatch(r'lib[\w.+-]+\.so(\.\d+)*', soname):
        raise FmuBinaryError(f'a stand-in name must be a soname like libname.so.3, got '
                             f'{soname!r}')
    c_file, version_script = _sources(pathlib.Path(source))
    digest = hashlib.sha256(soname.encode())
    for path in (c_file, version_script):
        if path is not None:
            digest.update(path.name.encode())
            digest.update(path.read_bytes())
    target = fmu_cache.cache_dir() / STAND_IN / digest.hexdigest()[:16] / soname
    if target.is_file():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = pathlib.Path(tempfile.mkdtemp(prefix=fmu_cache.STAGING_PREFIX, dir=target.parent))
    try:
        built = staging / soname
        command = ['gcc', '-O2', '-shared', '-fPIC', f'-Wl,-soname,{soname}',
                   *([f'-Wl,--version-script={version_script}'] if version_script else []),
                   '-o', str(built), str(c_file)]
        try:
            result = subprocess.run(command, capture_output=True, text=True, check=False)
        except FileNotFoundError as error:
            raise FmuBinaryError(f'building the stand-in {soname} needs gcc: {error}') from None
        if result.returncode != 0:
            raise FmuBinaryError(f'building the stand-in {soname} failed: {" ".join(command)}: '
                                 f'{" ".join(result.stderr.split())[:400]}')
        os.replace(built, target)
        logger.info('built the stand-in %s from %s: %s', soname, c_file, target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return target


def _check_key(binary: pathlib.Path, libraries: Sequence[Library],
               before: Sequence[str]) -> str:
    digest = hashlib.sha256(fmu_cache.file_sha256(binary).encode())
    for library in libraries:
        digest.update(repr(library).encode())
    for name in before:
        digest.update(name.encode())
    return digest.hexdigest()[:32]


def _load_in_child(binary: pathlib.Path, libraries: Sequence[str]) -> None:
    """Load ``binary`` after ``libraries`` in a child process; raise what went wrong."""
    command = [sys.executable, '-I', '-S', '-c', _CHILD, str(binary), *libraries]
    try:
        result = subprocess.run(command, capture_output=True, text=True, check=False,
                                timeout=LOAD_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise FmuBinaryError(f'loading {binary} did not end within {LOAD_TIMEOUT_S:g} s') \
            from None
    if result.returncode == 0:
        return
    loading = (result.stdout.strip().splitlines() or [str(binary)])[-1]
    what = 'the FMU binary' if loading == str(binary) else 'the preloaded library'
    if result.returncode < 0:
        try:
            name = signal.Signals(-result.returncode).name
        except ValueError:
            name = f'signal {-result.returncode}'
        raise FmuBinaryError(f'{what} {loading} is damaged: loading it killed a test process '
                             f'with {name} (a truncated or corrupt shared library: export or '
                             'download the FMU again)')
    message = ' '.join(result.stderr.split())
    if result.returncode != _REFUSED:
        raise FmuBinaryError(f'loading {what} {loading} failed (exit {result.returncode}): '
                             f'{message[-400:]}')
    missing = _MISSING.search(message)
    if missing:
        name = missing.group(1)
        raise FmuBinaryError(
            f'{what} {loading} needs the library {name}, which this host does not have: '
            f'install it (the distribution package that ships {name}), or name a copy under '
            f"the card's `preload` (a path), or carry the source of a stand-in "
            f'(`preload: [{{soname: {name}, source: DIR}}]`, DIR with one C file and a '
            f'version script)', missing=name)
    version = _VERSION.search(message)
    if version:
        raise FmuBinaryError(f'{what} {loading} needs the symbol version {version.group(1)}, '
                             f'which the library installed under that name lacks ({message}); '
                             "preload a library (or a stand-in's source) that provides it "
                             "under the card's `preload`")
    raise FmuBinaryError(f'{what} {loading} does not load: {message}')


def check_binary(folder: str | os.PathLike, model_identifier: str,
                 libraries: Sequence[Library] = (), label: str = '') -> tuple[str, ...]:
    """
    Load an FMU's binary in a child process first; then preload its libraries here.

    The child loads every library this process preloaded, then ``libraries`` (stand-ins
    built as needed; one without a ``soname`` stands in for the library the binary is found
    to lack), then the binary, and finds its FMI 2.0 entry points. When it loaded, the
    libraries are preloaded into this process (:func:`preload`) and the result is kept in
    the cache, so the next check of the same binary and libraries only hashes the binary.

    Parameters
    ----------
    folder : path
        The extracted FMU.
    model_identifier : str
        The binary's name (the FMI ``modelIdentifier``).
    libraries : sequence of Library
        To preload before the binary.
    label : str
        The FMU's name in messages (default: the folder).

    Returns
    -------
    tuple of str
        The libraries preloaded for this binary (paths or names).

    Raises
    ------
    FmuBinaryError
        One line: the binary is missing, lacks a library (named, with how to provide it),
        killed the child with a signal, or does not load.

    """
    label = label or str(folder)
    binary = binary_file(folder, model_identifier)
    if not binary.is_file():
        platform, _ = fmu_cache.platform()
        held = sorted(p.name for p in (pathlib.Path(folder) / 'binaries').glob('*'))
        raise FmuBinaryError(f'{label}: no binary for this platform: expected {binary} (the '
                             f'FMU holds binaries for {held}, this host needs {platform})')
    before = preloaded()
    key = _check_key(binary, libraries, before)
    record = fmu_cache.cache_dir() / CHECKED / key
    try:
        resolved = tuple(json.loads(record.read_text(encoding='utf-8')))
    except (OSError, ValueError, TypeError):
        resolved = None
    if resolved is None:
        resolved = _resolve(binary, libraries, before, label)
        try:
            record.parent.mkdir(parents=True, exist_ok=True)
            record.write_text(json.dumps(list(resolved)), encoding='utf-8')
        except OSError as error:  # a read-only cache: checked again next time
            logger.debug('binary check of %s not cached: %s', binary, error)
    preload(resolved)
    return resolved


def _resolve(binary: pathlib.Path, libraries: Sequence[Library], before: Sequence[str],
             label: str) -> tuple[str, ...]:
    """Return the libraries to preload with which ``binary`` loads in a child process."""
    resolved: list[str] = []
    open_stand_ins = []
    for library in libraries:
        if library.path is not None:
            resolved.append(library.path)
        elif library.soname is not None:
            resolved.append(str(stand_in(library.source, library.soname)))
        else:
            open_stand_ins.append(library)
    while True:
        try:
            _load_in_child(binary, [*before, *resolved])
        except FmuBinaryError as error:
            if error.missing is None or not open_stand_ins:
                raise FmuBinaryError(f'{label}: {error}', error.missing) from None
            library = open_stand_ins.pop(0)
            logger.info('%s needs %s: building it from %s', label, error.missing,
                        library.source)
            resolved.append(str(stand_in(library.source, error.missing)))
            continue
        logger.debug('%s loads (preloading %s)', binary, resolved)
        return tuple(resolved)
