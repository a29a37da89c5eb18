"""
Test FMUs of the model-card tests, built from ``tests/fmus/`` with gcc (not by the runtime).

- ``zone``: an R1C1 zone with names of its own (state ``cair.T``, inputs ``solrad, Tout, occ,
  q``, no ``dpos``; outputs ``T, Qr``), Model Exchange and Co-Simulation;
- ``zone2``: the same zone with a second control, a cooler ``Pcool`` in kW behind the overwrite
  switch ``Pcool_activate`` (Boolean).

Each FMU is built once per source hash into ``$MSHOOT_FMU_DIR/tests`` (the FMU cache's base),
so test sessions share the build.
"""
from __future__ import annotations

import hashlib
import os
import pathlib
import shutil
import uuid

from mshoot_core.fmu_build import CFLAGS, compile_library, pack_fmu
from mshoot_core.fmu_cache import cache_dir, FMI2_HEADERS, MODEL_HEADER, platform, SOURCE_DIR

FMU_SOURCES = pathlib.Path(__file__).resolve().parent / 'fmus'
#: name -> (model identifier, C file, modelDescription template, compiler defines)
TEST_FMUS = {
    'zone': ('Zone', 'zone.c', 'zone.xml', ()),
    'zone2': ('Zone2', 'zone.c', 'zone2.xml', ('-DTWO_CONTROLS',)),
    'zone_cs': ('ZoneCs', 'zone.c', 'zone_cs.xml', ()),  # Co-Simulation only
}


def build_test_fmu(name: str) -> pathlib.Path:
    """Return the test FMU ``name`` (a key of :data:`TEST_FMUS`), built if not built yet."""
    identifier, c_file, template, defines = TEST_FMUS[name]
    sources = [FMU_SOURCES / c_file, FMU_SOURCES / template,
               *(SOURCE_DIR / h for h in (MODEL_HEADER, *FMI2_HEADERS))]
    digest = hashlib.sha256()
    for path in sources:
        digest.update(path.read_bytes())
    digest.update(' '.join((*CFLAGS, *defines)).encode())
    key = digest.hexdigest()[:16]
    target = cache_dir() / 'tests' / key / f'{identifier}.fmu'
    if target.is_file():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    guid = '{' + str(uuid.uuid5(uuid.NAMESPACE_URL, f'mshoot-test-fmu:{name}:{key}')) + '}'
    library = target.parent / f'.{os.getpid()}' / f'{identifier}{platform()[1]}'
    library.parent.mkdir(exist_ok=True)
    compile_library(FMU_SOURCES / c_file, library, f'the {name} test FMU',
                    [*defines, f'-DMODEL_GUID="{guid}"'])
    description = (FMU_SOURCES / template).read_text(encoding='utf-8')
    description = description.replace('@GUID@', guid)
    description = description.replace('@DATETIME@', '2026-01-01T00:00:00Z')
    pack_fmu(target, description, library)
    shutil.rmtree(library.parent)
    return target
