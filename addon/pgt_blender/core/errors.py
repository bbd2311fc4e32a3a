"""The one error type bad input raises, so every front end can report it the same way."""

from pathlib import Path


class InputError(ValueError):
    """Bad input: ``str(error)`` is one line, ``"<path>: <problem>"``.

    Operators report it and return ``{'CANCELLED'}``; command-line scripts print it
    to stderr and exit non-zero.
    """

    def __init__(self, path, problem: str):
        self.path = Path(path)
        self.problem = " ".join(str(problem).split())  # keep it on one line
        super().__init__(f"{self.path}: {self.problem}")
