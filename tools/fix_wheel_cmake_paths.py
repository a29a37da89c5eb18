"""
Rewrite the build-machine paths hard-coded in the ROS 2 Jazzy message wheels.

The PyPI wheels export CMake targets whose include directories point at
``/opt/python/cp311-cp311/...`` (the manylinux build image). Building a custom
interface package against them fails with "Imported target ... includes
non-existent path". This rewrites every Python and numpy include directory
named in those files, inside the given venv only, to this interpreter's
include directory and this venv's numpy, then checks that each is right.

Files are replaced, never edited in place: installers such as uv hard-link
venv files to their cache, and an in-place edit would change the cache too.
"""
import pathlib
import re
import sys
import sysconfig

import numpy

NUMPY_INCLUDE = re.compile(r'[^";]*/numpy/_core/include')
PYTHON_INCLUDE = re.compile(r'[^";]*/include/python3\.\d+')


def main(venv: str) -> int:
    share = pathlib.Path(venv) / 'share'
    numpy_include = numpy.get_include()
    python_include = sysconfig.get_paths()['include']
    fixed = 0
    for path in sorted(share.glob('*/cmake/*.cmake')):
        text = path.read_text()
        if 'INTERFACE_INCLUDE_DIRECTORIES' not in text:
            continue
        new = NUMPY_INCLUDE.sub(lambda m: numpy_include, text)
        new = PYTHON_INCLUDE.sub(lambda m: python_include, new)
        if new != text:
            path.unlink()  # break any hard link to an installer's cache
            path.write_text(new)
            fixed += 1
    wrong = []
    for path in share.glob('*/cmake/*.cmake'):
        text = path.read_text()
        for pattern, expected in ((NUMPY_INCLUDE, numpy_include),
                                  (PYTHON_INCLUDE, python_include)):
            wrong += [f'{path}: {m}' for m in pattern.findall(text) if m != expected]
    if wrong:
        sys.stderr.write('include paths left wrong:\n  ' + '\n  '.join(wrong) + '\n')
        return 1
    sys.stdout.write(f'[setup] include paths of the message wheels point at this venv '
                     f'({fixed} CMake files rewritten)\n')
    return 0


if __name__ == '__main__':
    if len(sys.argv) != 2:
        sys.stderr.write('usage: fix_wheel_cmake_paths.py VENV\n')
        sys.exit(2)
    sys.exit(main(sys.argv[1]))
