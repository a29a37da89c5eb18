"""
Build the time-dependent test FMU (``tests/fmus/timed_zone.c``) with gcc, for the tests.

Two variants from the same C file: with and without FMU-state support declared
in the modelDescription (``canGetAndSetFMUstate``), so both ways an interval
or a plant starts are exercised. Built once per session into a temporary
folder by the ``timed_fmus`` fixture of ``conftest.py``.
"""
from __future__ import annotations

import pathlib
import subprocess
import uuid
import zipfile

from mshoot_core import fmu_build, fmu_cache

SOURCES = pathlib.Path(__file__).resolve().parent / 'fmus'
IDENTIFIER = 'TimedZone'
#: Model inputs, states and outputs of the FMU under the names the tests use.
VARIABLES = {'inputs': ('Tout', 'q'), 'states': {'T': 'zone.T'},
             'outputs': ('T', 'Eint', 'Pint')}


def build_timed_fmu(out_dir: pathlib.Path, can_get_state: bool = True) -> pathlib.Path:
    """Compile the FMU into ``out_dir/TimedZone[_nostate].fmu`` and return its path."""
    platform_dir, suffix = fmu_cache.platform()
    variant = '' if can_get_state else '_nostate'
    work = out_dir / f'build{variant}'
    work.mkdir(parents=True, exist_ok=True)
    guid = '{' + str(uuid.uuid5(uuid.NAMESPACE_URL, f'mshoot-test:{IDENTIFIER}{variant}')) + '}'
    library = work / f'{IDENTIFIER}{suffix}'
    command = [fmu_build.find_compiler(), *fmu_build.CFLAGS, f'-DMODEL_GUID="{guid}"', '-I',
               str(fmu_cache.SOURCE_DIR), '-o', str(library), str(SOURCES / 'timed_zone.c'),
               '-lm']
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    if result.returncode != 0 or result.stderr.strip():
        raise RuntimeError(f'compiling the test FMU failed:\n{result.stderr}')
    description = (SOURCES / 'timed_zone.xml').read_text().replace('@GUID@', guid).replace(
        '@CAN_STATE@', 'true' if can_get_state else 'false')
    target = out_dir / f'{IDENTIFIER}{variant}.fmu'
    # fixed dates: the same sources give the same bytes, so one folder in the extraction cache
    with zipfile.ZipFile(target, 'w', compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in (('modelDescription.xml', description.encode()),
                           (f'binaries/{platform_dir}/{library.name}', library.read_bytes())):
            archive.writestr(zipfile.ZipInfo(name, date_time=(2020, 1, 1, 0, 0, 0)), data,
                             compress_type=zipfile.ZIP_DEFLATED)
    return target
