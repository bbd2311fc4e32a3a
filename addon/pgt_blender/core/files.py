"""Output files that appear complete or not at all."""

import os
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_output(path):
    """A binary stream to a temporary file beside ``path``, renamed onto ``path`` when
    the block ends without error and removed otherwise. A failed write (disk full,
    permission) raises OSError naming ``path``, not the temporary file."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.partial")
    try:
        with open(temporary, "wb") as stream:
            yield stream
        os.replace(temporary, path)
    except OSError as error:
        if error.filename not in (None, str(temporary)):
            raise
        raise OSError(error.errno, error.strerror, str(path)) from error
    finally:
        temporary.unlink(missing_ok=True)
