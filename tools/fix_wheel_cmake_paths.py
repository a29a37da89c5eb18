"""Rewrite the build-machine paths hard-coded in the ROS 2 Jazzy message wheels.

The PyPI wheels export CMake targets whose include directories point at
``/opt/python/cp311-cp311/...`` (the manylinux build image). Building a custom
interface package against them fails with "Imported target ... includes
non-existent path". This rewrites those paths, inside the given venv only, to
this interpreter's include directory and numpy's, then checks none is left.
"""
import pathlib
import sys
import sysconfig

import numpy

BUILD_PY_INCLUDE = '/opt/python/cp311-cp311/include/python3.11'
BUILD_NUMPY_INCLUDE = '/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include'


def main(venv: str) -> int:
    share = pathlib.Path(venv) / 'share'
    replacements = {
        BUILD_NUMPY_INCLUDE: numpy.get_include(),
        BUILD_PY_INCLUDE: sysconfig.get_paths()['include'],
    }
    fixed = 0
    for path in share.glob('*/cmake/*.cmake'):
        text = path.read_text()
        if '/opt/python/cp311-cp311' not in text:
            continue
        for old, new in replacements.items():
            text = text.replace(old, new)
        path.write_text(text)
        fixed += 1
    left = [str(p) for p in share.glob('*/cmake/*.cmake')
            if '/opt/python/cp311-cp311' in p.read_text()]
    if left:
        sys.stderr.write('build-machine paths left in:\n  ' + '\n  '.join(left) + '\n')
        return 1
    sys.stdout.write(f'[setup] fixed build-machine paths in {fixed} CMake files\n')
    return 0


if __name__ == '__main__':
    if len(sys.argv) != 2:
        sys.stderr.write('usage: fix_wheel_cmake_paths.py VENV\n')
        sys.exit(2)
    sys.exit(main(sys.argv[1]))
