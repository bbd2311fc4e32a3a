"""Plumbing of headless_scripts/ that needs no bpy: the same script runs as
``blender -b [file.blend] -P script.py -- ARGS`` and as ``python script.py ARGS``."""

import sys


def script_argv() -> list:
    """The script's own arguments: those after ``--`` (Blender's convention), else argv[1:]."""
    return sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
