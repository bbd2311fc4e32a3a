"""Argument handling, errors and exit codes of the command-line package (``commands/``):
the same command runs as a console script (``pgt-export-bank ARGS``), as
``python headless_scripts/export_bank.py ARGS`` and as
``blender -b [file.blend] -P headless_scripts/export_bank.py -- ARGS``, and reports bad
input as one line and exit code 1. Benchmark helpers live in dev.py, which does not ship."""

import argparse
import atexit
import math
import os
import sys

from .core.learning import MAX_CLOUD_POINTS


def script_argv() -> list:
    """The script's own arguments: those after ``--`` (Blender's convention), else argv[1:]."""
    return sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]


def exit(code: int) -> None:
    """End a script with ``code``. Blender 4.2's bpy module ends a process that
    registered a Python callback property (update, search, dynamic enum items) with
    SIGSEGV, losing the code: C++ static destructors free its UI types through Python
    after Python has shut down. There, Python's exit handlers run here and the process
    ends before those destructors."""
    bpy = sys.modules.get("bpy")  # never imported here: core-only scripts stay bpy-free
    if bpy is not None and bpy.app.version < (4, 5, 0):
        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


def run_main(main, argv: list) -> int:
    """``main(argv)``'s exit code, with a bad input (InputError) or a failed read or write
    (OSError: a folder where a file should be, a full disk, no permission) printed as the
    one line ``error: <file>: <problem>`` and exit code 1 instead of a traceback; memory
    running out, as ``error: out of memory: <what>``; Ctrl-C as ``error: interrupted`` (then
    ``; <what is left to do>`` where a command says) and exit code 130. A warning is one line too,
    ``warning: <message>`` (Python's own form adds the source line that raised it)."""
    import warnings

    from .core.errors import InputError

    try:
        with warnings.catch_warnings():
            warnings.showwarning = _one_line_warning
            return main(argv)
    except InputError as error:
        print(f"error: {error}", file=sys.stderr)
    except OSError as error:
        print(f"error: {error.filename or '-'}: {error.strerror or error}", file=sys.stderr)
    except KeyboardInterrupt as interrupt:  # Ctrl-C: every output is written whole or not at all, so no traceback
        print("; ".join(("error: interrupted", *map(str, interrupt.args))), file=sys.stderr)
        return 130
    except (MemoryError, RuntimeError) as error:
        problem = _memory_problem(error)
        if problem is None:
            raise
        print(f"error: out of memory: {problem}", file=sys.stderr)
    return 1


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    suffix = "" if category is UserWarning else f" ({category.__name__})"
    print(f"warning: {' '.join(str(message).split())}{suffix}", file=file or sys.stderr)


def _memory_problem(error: BaseException):
    """What ran out, for numpy's MemoryError and torch's allocator failures (a
    RuntimeError: "DefaultCPUAllocator: can't allocate memory: ...", "CUDA out of
    memory"); None for any other error, which stays a traceback."""
    text = " ".join(str(error).split())
    if isinstance(error, MemoryError):
        return text or "MemoryError"
    if "can't allocate memory" in text or "out of memory" in text:
        return text.split("DefaultCPUAllocator: ")[-1]
    return None


def markdown_table(header: list, rows: list, align: str = "") -> str:
    """A Markdown table of ``header`` (C,) column titles and ``rows`` of C cells each
    (written with str()); ``align`` one letter per column, "l" left or "r" right
    (default: the first column left, the others right)."""
    align = align or "l" + "r" * (len(header) - 1)
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" if a == "l" else "---:" for a in align) + "|"]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def launch(name: str) -> None:
    """Run the command ``name`` (commands/<name>.py: its ``main(argv) -> int``) on the
    script's arguments (script_argv) and end with its code through :func:`exit`. The
    module is imported under run_main, so Ctrl-C while its libraries load (bpy, scipy,
    torch: up to a second) is ``error: interrupted`` too, not a traceback. The
    headless_scripts/ shims call it, and the console scripts (pyproject.toml) through
    ``launchers``."""
    import importlib

    def main(argv: list) -> int:
        return importlib.import_module(f".commands.{name}", __package__).main(argv)

    exit(run_main(main, script_argv()))


class _Launchers:
    """``launchers.<name>()`` launches the command ``name``: the console scripts' entry
    points (``pgt_blender.cli:launchers.export_bank``), which this module, light to
    import, serves before any command's libraries load."""

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        return lambda: launch(name)


launchers = _Launchers()


class _DefaultsShown(argparse.HelpFormatter):
    """--help that states each option's default, unless its text already does or there
    is none to state (None, False, empty, or a switch: "--no-refine (default: True)"
    would read as refinement off)."""

    def _get_help_string(self, action) -> str:
        default, text = action.default, action.help
        stated = default is None or default is False or default is argparse.SUPPRESS or action.nargs == 0 \
            or (isinstance(default, (str, list, tuple)) and not default) or "default" in text.lower()
        return text if stated or not action.option_strings else text + " (default: %(default)s)"


def parser(prog: str, doc: str) -> argparse.ArgumentParser:
    """The argument parser of a command or benchmark ``prog``: its docstring's first
    paragraph as the description, each option's default stated in --help."""
    return argparse.ArgumentParser(prog=prog, description=doc.split("\n\n")[0], formatter_class=_DefaultsShown)


def convention_option(parser: argparse.ArgumentParser, flag: str, database: str, note: str = "") -> None:
    """Add ``flag``: how the ground-truth database ``database`` (an option's name) stores
    its points (core.gt_database.CONVENTIONS), read from the file when not given."""
    parser.add_argument(flag, choices=("openpcdet", "mmdet3d"),
                        help=f"how {database} stores points: about the box centre (openpcdet) or its bottom centre "
                             f"(mmdet3d); default: read from the file, where mmdet3d's infos carry a group_id each"
                             + note)


def finite(text: str) -> float:
    """A finite number, as an argparse type (NaN and infinities are refused)."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got '{text}'")
    return value


def within(low: float, high: float):
    """An argparse type: a finite number in ``low`` .. ``high`` (a physical quantity;
    1e308 m would overflow the arithmetic it enters)."""
    def parse(text: str) -> float:
        value = finite(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected a number {low:g} .. {high:g}, got '{text[:40]}'")
        return value
    return parse


def whole(low: int, high: int):
    """An argparse type: a whole number in ``low`` .. ``high``. Every count a command
    takes is bounded, so that a typo (10**9 steps, a negative seed) is a usage error,
    not a MemoryError, an endless run or a traceback deep inside a library."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:  # also beyond 4,300 digits
            value = None
        if value is None or not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected a whole number {low:,} .. {high:,}, got '{text[:40]}'")
        return value
    return parse


SEED = whole(0, 2**31 - 1)  # numpy, torch and COLMAP (a C int) all take it
THREADS = whole(1, 64)
STEPS = whole(1, 10**7)  # optimiser steps
CLOUD_POINTS = whole(1, MAX_CLOUD_POINTS)  # points per cloud a network sees


def output(folder: bool, suffixes: tuple = ()):
    """An argparse type: a path where the command can write its output file, named with
    one of ``suffixes`` (``folder``: its output folder), checked before any work
    (files.output_path)."""
    def parse(text: str):
        from .core.errors import InputError
        from .core.files import output_path

        try:
            return output_path(text, folder, suffixes)
        except InputError as error:
            raise argparse.ArgumentTypeError(str(error)) from None
    return parse


def output_file(*suffixes: str):
    """An argparse type: an output file named with one of ``suffixes`` (see ``output``)."""
    return output(False, suffixes)


OUTPUT_FOLDER = output(folder=True)
