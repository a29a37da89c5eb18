"""An FMU binary's own symbols win over a library loaded into the global scope before it."""
import os
import pathlib
import shutil
import subprocess
import sys

import pytest

#: A library that exports ``lapack_like`` (as CasADi's OpenBLAS exports ``dgesv_``).
GLOBAL_C = 'int lapack_like(void) { return 1; }\n'
#: A binary that defines ``lapack_like`` too and calls it (as the heat pump FMU calls its own).
BINARY_C = ('int lapack_like(void) { return 2; }\n'
            'int which_lapack(void) { return lapack_like(); }\n')
#: Run in a child (the global scope of this process is left alone): load the global library
#: RTLD_GLOBAL, then the binary plainly or through fmu_binary.isolated; print what it calls.
CHILD = r"""
import ctypes, sys
from mshoot_core import fmu_binary
ctypes.CDLL(sys.argv[1], mode=ctypes.RTLD_GLOBAL)
if sys.argv[3] == 'isolated':
    with fmu_binary.isolated(sys.argv[2]) as path:
        binary = ctypes.CDLL(str(path))
else:
    binary = ctypes.CDLL(sys.argv[2])
print(binary.which_lapack())
"""


def build(source: str, path: pathlib.Path) -> pathlib.Path:
    c_file = path.with_suffix('.c')
    c_file.write_text(source)
    subprocess.run(['gcc', '-shared', '-fPIC', '-o', str(path), str(c_file)], check=True)
    return path


@pytest.mark.skipif(shutil.which('gcc') is None or not hasattr(os, 'RTLD_DEEPBIND'),
                    reason='needs gcc and RTLD_DEEPBIND (glibc)')
def test_an_isolated_binary_calls_its_own_symbols(tmp_path):
    global_library = build(GLOBAL_C, tmp_path / 'libglobal.so')
    binary = build(BINARY_C, tmp_path / 'binary.so')

    def which(how: str) -> int:
        done = subprocess.run([sys.executable, '-c', CHILD, str(global_library), str(binary),
                               how], capture_output=True, text=True, check=True)
        return int(done.stdout.strip())

    assert which('plain') == 1  # the global scope wins: what the isolation is for
    assert which('isolated') == 2
