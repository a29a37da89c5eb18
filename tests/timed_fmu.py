"""
Build the time-dependent test FMU (``tests/fmus/timed_zone.c``) with gcc, for the tests.

Two variants from the same C file: with and without FMU-state support declared
in the modelDescription (``canGetAndSetFMUstate``), so both ways an interval
or a plant starts are exercised. Built once per session into a temporary
folder by the ``timed_fmus`` fixture of ``conftest.py``.
"""
from __future__ import annotations

import pathlib
import uuid

from mshoot_core import fmu_build, fmu_cache

SOURCES = pathlib.Path(__file__).resolve().parent / 'fmus'
IDENTIFIER = 'TimedZone'
#: Model inputs, states and outputs of the FMU under the names the tests use.
VARIABLES = {'inputs': ('Tout', 'q'), 'states': {'T': 'zone.T'},
             'outputs': ('T', 'Eint', 'Pint')}


def build_timed_fmu(out_dir: pathlib.Path, can_get_state: bool = True) -> pathlib.Path:
    """Compile the FMU into ``out_dir/TimedZone[_nostate].fmu`` and return its path."""
    variant = '' if can_get_state else '_nostate'
    work = out_dir / f'build{variant}'
    work.mkdir(parents=True, exist_ok=True)
    guid = '{' + str(uuid.uuid5(uuid.NAMESPACE_URL, f'mshoot-test:{IDENTIFIER}{variant}')) + '}'
    library = work / f'{IDENTIFIER}{fmu_cache.platform()[1]}'
    if fmu_build.compile_library(SOURCES / 'timed_zone.c', library, 'the test FMU',
                                 [f'-DMODEL_GUID="{guid}"']):
        raise RuntimeError('the test FMU compiles with warnings (logged)')
    description = (SOURCES / 'timed_zone.xml').read_text().replace('@GUID@', guid).replace(
        '@CAN_STATE@', 'true' if can_get_state else 'false')
    return fmu_build.pack_fmu(out_dir / f'{IDENTIFIER}{variant}.fmu', description, library)
