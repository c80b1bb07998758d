#!/usr/bin/env python3
"""Rewrite the wheel builder's Python paths in the venv's CMake export files.

Some ROS 2 Jazzy wheels ship `*.cmake` files that name the builder's interpreter, e.g.
`/opt/python/cp311-cp311/include/python3.11` and
`/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include`. A colcon build of a
rosidl package then fails to find Python.h / numpy headers. This script points them at this
interpreter's include directory and this venv's numpy, and prints how many files it changed.
Idempotent: a second run changes nothing.

usage: fix_cmake_paths.py VENV
"""
import argparse
import pathlib
import re
import sys
import sysconfig

import numpy

BUILDER = re.compile(r'/opt/python/cp3\d+-cp3\d+')


def fix(venv: pathlib.Path) -> int:
    include = sysconfig.get_paths()['include']
    numpy_include = numpy.get_include()
    numpy_re = re.compile(
        BUILDER.pattern + r'/lib/python3\.\d+/site-packages/numpy/(_core|core)/include')
    include_re = re.compile(BUILDER.pattern + r'/include/python3\.\d+')
    changed = 0
    for path in (venv / 'share').rglob('*.cmake'):
        text = path.read_text(errors='surrogateescape')
        if '/opt/python/' not in text:
            continue
        new = include_re.sub(include, numpy_re.sub(numpy_include, text))
        if BUILDER.search(new):
            raise SystemExit(f'{path}: a builder path is left that this script does not know')
        if new != text:
            path.write_text(new, errors='surrogateescape')
            changed += 1
    return changed


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0],
                                     epilog='Idempotent: a second run changes nothing.')
    parser.add_argument('venv', help='the virtual environment whose share/ to fix')
    args = parser.parse_args(argv)
    venv = pathlib.Path(args.venv)
    if not (venv / 'share').is_dir():
        parser.error(f'{venv} has no share/ folder: not a venv with ROS wheels')
    print(f'fix_cmake_paths: rewrote {fix(venv)} CMake file(s)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
