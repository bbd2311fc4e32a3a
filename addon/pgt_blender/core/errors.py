"""The one error type bad input raises, so every front end can report it the same way."""

import math
from pathlib import Path


def finite_number(value) -> bool:
    """True for an int or float that is finite as a float (a bool is not a number here,
    nor an integer too large for a float)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def printable(text: str) -> str:
    """``text`` with any lone surrogate (how Python holds the undecodable bytes of a file
    name, or a JSON "\\udcff") written as its escape: UTF-8 can encode it, as Blender's
    reports, names and strings need."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


def one_line(text: str) -> str:
    """``printable(text)`` with its line breaks written as escapes: a report or error
    that names a file or object stays one line whatever the name holds."""
    return printable(text.replace("\r", "\\r").replace("\n", "\\n"))


class InputError(ValueError):
    """Bad input: ``str(error)`` is one line, ``"<path>: <problem>"``.

    Operators report it and return ``{'CANCELLED'}``; command-line scripts print it
    to stderr and exit non-zero.
    """

    def __init__(self, path, problem: str):
        self.path = Path(path)
        self.problem = " ".join(str(problem).split())  # keep it on one line
        super().__init__(one_line(str(self.path)) + ": " + printable(self.problem))
