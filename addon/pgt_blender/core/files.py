"""Output files that appear complete or not at all."""

import os
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_output(path):
    """A binary stream to a temporary file beside ``path``, renamed onto ``path`` when
    the block ends without error and removed otherwise."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.partial")
    try:
        with open(temporary, "wb") as stream:
            yield stream
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
